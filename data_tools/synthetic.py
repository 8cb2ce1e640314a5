"""Synthetic dynamic scenes with exact ground truth: the fixture of the tests, the demo input and
the accuracy benchmark of the visual odometry.

A scene is a textured street seen by a moving pinhole camera, with static crates, pillars and
blocks, and 0 to 3 rigid movers (people and cars). Everything is drawn from
``np.random.default_rng([seed, stream])``, with separate streams for the camera, the street, the
movers and each texture (no global random state), so a :class:`SceneConfig` fixes every pixel.

World and units
    Metres and frames. World frame: x across the street, y DOWN (gravity), z along the street; the
    floor is the plane y = 0, so heights are negative y. The street is closed on all six sides
    (floor, "sky" ceiling 7-9 m up, side walls 12-16 m apart, end walls 4-7 m behind the first and
    25-35 m ahead of the last camera position), so every pixel has a finite depth (about 1 to 45
    m). Poses are ``T_world_cam`` in the OpenCV camera frame (:mod:`mona_vo.conventions`); frame
    0 is neither at the origin nor axis-aligned.

Geometry
    Every object is an oriented box (the street box is seen from inside). One ray per pixel
    centre (pixel centres at integer coordinates) is intersected analytically with each box (slab
    test in the box frame, only inside the box's projected bounding rectangle), keeping the
    nearest hit. Depth is that hit's exact camera z (float64 math, stored float32); the mask is
    "the nearest hit is a mover". Silhouettes are not anti-aliased: each pixel shows exactly the
    surface its centre ray hits, so image, depth, mask and ids agree pixel by pixel.

Texture and shading
    Each material is a periodic, band-limited colour noise (amplitude spectrum f^-0.8 times a
    Gaussian cut-off at a wavelength of 5 texels; luminance std 28, chroma std 5 grey levels),
    1024^2 texels (street, movers) or 512^2 (static boxes), sampled bilinearly at the face
    coordinates in metres times texels per metre. Texels per metre follow the focal length
    (0.08 fx on the street, 0.06 fx on the sky, 0.14 fx on static boxes, 0.16 fx on movers; at
    fx = 800 a finest wavelength of 8, 10, 4.5 and 4 cm), so images of any size have the same
    pixel statistics. Colour is albedo times a constant brightness per face (flat shading), so a
    static point's colour does not depend on the view as long as the texture is not minified.
    Anti-aliasing keeps the texture's cut-off wavelength at 4 pixels or more in every direction:
    where the pixel footprint (ellipse of the analytic texel-per-pixel Jacobian) exceeds 1.25
    texels, trilinear mip-mapping (levels built in the Fourier domain) plus a Gaussian along the
    footprint's major axis (up to 8:1 anisotropy from the mip-map, beyond by taps). Far and
    grazing surfaces are therefore smoother, and their colour changes a little with distance, as
    with a real lens. Movers use saturated paint and clothing colours, the world muted greys and
    browns; the texture statistics are the same.

Camera
    Sums of low-frequency sinusoids of the frame index: forward 0.05-0.25 m/frame (+-25 %),
    sideways sway up to 1.5 m, a small vertical bob, yaw 0.4-1.1 deg/frame peak, pitch and roll
    below that. ``fast-rotation`` pans: yaw swings +-30-60 deg at a peak of 4-6 deg/frame (median
    over frames of the rotation 3-4.5 deg), pitch peaks at 2-3 deg/frame, forward 0.03-0.08
    m/frame. Intrinsics: fx = fy from a horizontal field of view of 55-75 deg, principal point
    within 2 % of the image centre, constant over the sequence. The camera, street and static boxes
    depend only on the seed, n_frames, the aspect ratio and the preset's camera model, so
    ``static``, ``one-large`` and ``several`` with one seed show the same street and path.

Movers
    Upright boxes standing on the floor: people about 0.5 x 1.8 x 0.35 m walking 0.025-0.06
    m/frame, cars about 1.8 x 1.5 x 4.3 m at 0.04-0.35 m/frame, heading along their velocity.
    Each is anchored a few metres in front of the camera at a mid-sequence frame (crossing, walking
    or driving along, oncoming, or keeping pace ahead of the camera), drawn again (at most 400
    times) until it keeps 1.2 m from every camera centre and 0.3 m from walls, static boxes and
    other movers, and meets the preset's coverage rule on a 128-pixel-wide ray-cast of the view
    (static boxes occlude). A scene that cannot be built raises :class:`MonaVoError` naming the
    seed. Checked on seeds 0-9: every preset builds up to 80 frames; beyond, one-large may fail.
"""
from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from pathlib import Path

import cv2
import numpy as np

from data_tools.atomic import atomic_path, write_text_atomic
from data_tools.sintel_formats import write_cam, write_dpt
from mona_vo.conventions import Intrinsics, make_pose, tum_row
from mona_vo.errors import MonaVoError

log = logging.getLogger(__name__)

PRESETS: dict[str, str] = {
    "static": "no moving objects: camera walking or driving down a textured street with crates, "
              "pillars and blocks",
    "one-large": "one large mover, a car or a person close to the camera, covering 15-45 % of the "
                 "image on at least 80 % of the frames, visible on all frames, never above 50 %",
    "several": "two or three movers (people and at most one car) at 2.5-15 m, each visible on at "
               "least 70 % of the frames, together at most 50 % of the image",
    "fast-rotation": "camera panning and tilting fast (peak yaw rate 4-6 deg/frame) while slowly "
                     "moving forward, with one mover visible on at least half of the frames",
}

# Coverage rules of the presets, on the coarse grid used while placing movers.
_ONE_LARGE_RANGE = (0.16, 0.44)      # fraction of the image; a little inside 15-45 % for the grid
_ONE_LARGE_IN_RANGE = 0.85           # fraction of frames whose coverage must be in that range
_MAX_COVERAGE = 0.46                 # fraction of the image, any frame, all movers together
_VISIBLE_COVERAGE = 0.002            # fraction of the image above which a mover counts as visible
_SEVERAL_VISIBLE_FRAMES = 0.7        # fraction of frames showing each mover of "several"
_FAST_VISIBLE_FRAMES = 0.5           # same for the mover of "fast-rotation"
_MAX_TRIES = 400                     # proposals per mover before giving up
_COVERAGE_GRID_WIDTH = 128           # pixels across of the coarse coverage grid

_CAMERA_CLEARANCE = 1.2              # metres from a camera centre to any mover
_STATIC_CLEARANCE = 1.5              # metres from the camera path to a static box (ground plane)
_GAP = 0.3                           # metres between movers, walls and static boxes

_FINEST_WAVELENGTH_TEXELS = 5.0      # Gaussian cut-off wavelength of every texture, texels
_MIN_WAVELENGTH_PX = 4.0             # that wavelength is kept at or above this many pixels
_MIP_FOOTPRINT = _FINEST_WAVELENGTH_TEXELS / _MIN_WAVELENGTH_PX  # texels per pixel at level 0
_SPECTRAL_SLOPE = 0.8                # amplitude ~ f^-slope (power ~ f^-1.6)
_MIN_LEVEL_SIZE = 8                  # texels across of the coarsest mip level
# Texels per metre = density * fx (pixels): the texture follows the focal length, so images of any
# size have the same pixel statistics (at fx = 800: finest wavelengths of 8, 6 and 5 cm).
_STREET_DENSITY = 0.08               # street walls and floor, texels per metre per pixel of fx
_SKY_DENSITY = 0.06                  # ceiling ("sky")
_STATIC_DENSITY = 0.14               # static boxes
_MOVER_DENSITY = 0.16                # movers
_CHUNK = 1 << 14                     # texture samples per vectorised batch
_TAP_SPACING = 2.0                   # filter taps at most this many mip footprints apart
_MAX_ANISOTROPY = 8                  # longest / shortest axis of the mip level's footprint
_LUM_STD = 28.0                      # texture luminance standard deviation, grey levels
_CHROMA_STD = 5.0                    # texture chroma standard deviation, grey levels

# Palettes, RGB 0-255: muted world surfaces, saturated movers.
_WORLD_COLOURS = ((128, 126, 120), (150, 138, 118), (140, 112, 98), (112, 116, 122),
                  (160, 152, 135), (118, 124, 108), (100, 100, 104), (135, 125, 110))
_SKY_COLOUR = (150, 175, 205)
_STATIC_COLOURS = ((150, 118, 80), (135, 135, 128), (95, 110, 120), (160, 140, 105),
                   (120, 100, 85))
_CAR_COLOURS = ((185, 40, 45), (40, 70, 170), (200, 170, 40), (45, 135, 70), (205, 110, 35),
                (120, 45, 150))
_PERSON_COLOURS = ((170, 50, 120), (45, 140, 160), (110, 60, 160), (200, 85, 70), (60, 100, 190),
                   (190, 160, 40))

# Face f of a box: axis f // 2, side -1 (f even) or +1 (f odd). Its texture axes are the other two.
_UV_AXES = ((1, 2), (0, 2), (0, 1))


@dataclass(frozen=True)
class SceneConfig:
    """What to render. Every field has a default; the preset is checked when the config is made."""

    width: int = 1024               # image width, pixels
    height: int = 436               # image height, pixels
    n_frames: int = 50              # number of frames
    preset: str = "one-large"       # scene kind, a name in PRESETS
    seed: int = 0                   # seed of every random choice (non-negative integer)
    hfov_deg: float | None = None   # horizontal field of view, degrees; None: drawn in [55, 75]

    def __post_init__(self):
        if self.preset not in PRESETS:
            raise ValueError(f"unknown preset {self.preset!r}; valid presets: "
                             f"{', '.join(PRESETS)}")
        if self.width < 16 or self.height < 16:
            raise ValueError(f"image size {self.width} x {self.height} is too small (at least 16)")
        if self.n_frames < 2:
            raise ValueError(f"n_frames must be at least 2, got {self.n_frames}")
        if not (isinstance(self.seed, (int, np.integer)) and self.seed >= 0):
            raise ValueError(f"seed must be a non-negative integer, got {self.seed!r}")
        if self.hfov_deg is not None and not 10.0 <= self.hfov_deg <= 150.0:
            raise ValueError(f"hfov_deg must be in [10, 150] degrees, got {self.hfov_deg}")


@dataclass(frozen=True, eq=False)
class RenderedFrame:
    """One rendered frame and its exact ground truth."""

    index: int                # frame number, from 0
    image: np.ndarray         # (H, W, 3) uint8 RGB
    depth: np.ndarray         # (H, W) float32 z of the visible surface in the camera frame, metres
    mask: np.ndarray          # (H, W) bool, True where the visible surface belongs to a mover
    object_id: np.ndarray     # (H, W) uint8: 0 static scene, k for mover k (1-based)
    face_id: np.ndarray       # (H, W) int16: 6 * box + face of the visible surface (box 0 street)
    T_world_cam: np.ndarray   # (4, 4) float64 camera-to-world pose
    intrinsics: Intrinsics    # pinhole intrinsics, pixels


# ----------------------------------------------------------------------------------------------
# Small geometry helpers


def _rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _waves(rng, t, rate, period_range, max_amplitude=np.inf):
    """A sinusoid of t (frames) with a period drawn in period_range (frames), random phase and
    peak rate ``rate`` per frame, or less where the amplitude would exceed ``max_amplitude``."""
    omega = 2.0 * np.pi / rng.uniform(*period_range)
    amplitude = min(rate / omega, max_amplitude)
    return amplitude * np.sin(omega * t + rng.uniform(0.0, 2.0 * np.pi))


def _footprint_corners(centre_xz, heading, half_xz):
    """(N, 4, 2) ground corners x, z of upright boxes with centres (N, 2) and headings (N,)."""
    c, s = np.cos(heading), np.sin(heading)
    ax = np.stack([c, -s], axis=-1)     # box x axis in (x, z): Ry(heading) e_x = (c, 0, -s)
    az = np.stack([s, c], axis=-1)      # box z axis in (x, z): Ry(heading) e_z = (s, 0, c)
    signs = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)
    return (centre_xz[:, None, :] + signs[None, :, 0:1] * half_xz[0] * ax[:, None, :]
            + signs[None, :, 1:2] * half_xz[1] * az[:, None, :])


def _footprints_overlap(corners_a, corners_b):
    """(N,) bool: whether convex quadrilaterals (N, 4, 2) overlap (separating axis test)."""
    overlap = np.ones(corners_a.shape[0], dtype=bool)
    for corners in (corners_a, corners_b):
        for k in range(2):
            edge = corners[:, k + 1] - corners[:, k]
            axis = np.stack([-edge[:, 1], edge[:, 0]], axis=-1)
            pa = np.einsum("nkc,nc->nk", corners_a, axis)
            pb = np.einsum("nkc,nc->nk", corners_b, axis)
            separated = (pa.max(1) < pb.min(1)) | (pb.max(1) < pa.min(1))
            overlap &= ~separated
    return overlap


def _point_box_distance(points, R, centre, half):
    """(N,) distances, metres, from points (N, 3) to boxes with poses R (N, 3, 3), centre (N, 3)."""
    local = np.einsum("nji,nj->ni", R, points - centre)
    outside = np.maximum(np.abs(local) - half, 0.0)
    return np.linalg.norm(outside, axis=1)


# ----------------------------------------------------------------------------------------------
# Textures


@lru_cache(maxsize=4)
def _spectral_filters(size: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per mip level k, the rfft-layout amplitude filters (size, size // 2 + 1) float32 of the
    luminance and chroma fields: f^-slope times a Gaussian cut-off at the level's wavelength."""
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.rfftfreq(size)[None, :]
    f = np.hypot(fx, fy)
    f[0, 0] = 1.0
    fc = 1.0 / _FINEST_WAVELENGTH_TEXELS
    power = f ** -_SPECTRAL_SLOPE
    power[0, 0] = 0.0
    out = []
    k = 0
    while size >> k >= _MIN_LEVEL_SIZE:
        fck = fc / 2 ** k
        out.append(((power * np.exp(-(f / fck) ** 2)).astype(np.float32),
                    (power * np.exp(-(2.0 * f / fck) ** 2)).astype(np.float32)))
        k += 1
    return out


class _Texture:
    """A periodic band-limited colour texture with its mip-map.

    Level k is the same periodic function low-passed to a cut-off wavelength of
    ``_FINEST_WAVELENGTH_TEXELS * 2**k`` level-0 texels, sampled every 2**k level-0 texels; texel j
    of any level sits at coordinate j (bilinear lookups wrap around).
    """

    def __init__(self, rng, size: int, base_rgb, lum_std: float, chroma_std: float):
        filters = _spectral_filters(size)
        shape = filters[0][0].shape
        # Field 0 (luminance) is broad band, fields 1 and 2 (chroma) an octave lower.
        noise = [rng.standard_normal(shape, dtype=np.float32)
                 + 1j * rng.standard_normal(shape, dtype=np.float32) for _ in range(3)]
        lum_dir = 1.0 + rng.uniform(-0.1, 0.1, 3)
        theta = rng.uniform(0.0, 2.0 * np.pi)
        e1 = np.array([1.0, -1.0, 0.0]) / np.sqrt(2.0)
        e2 = np.array([1.0, 1.0, -2.0]) / np.sqrt(6.0)
        ch1 = np.cos(theta) * e1 + np.sin(theta) * e2
        ch2 = -np.sin(theta) * e1 + np.cos(theta) * e2
        mix = np.stack([lum_std * lum_dir, chroma_std * ch1, chroma_std * ch2])  # (3 fields, 3 rgb)
        base = np.asarray(base_rgb, dtype=np.float32)

        self.levels: list[np.ndarray] = []   # level k: (S_k * S_k,) uint32, packed R, G, B, 0 bytes
        self.sizes: list[int] = []
        scale = None
        for k, (low_broad, low_chroma) in enumerate(filters):
            sk = size >> k
            half = sk // 2
            fields = []
            for j in range(3):
                s = noise[j] * (low_broad if j == 0 else low_chroma)
                if half < size // 2:
                    s = np.concatenate([s[:half, :half + 1], s[size - half:, :half + 1]], axis=0)
                fields.append(np.fft.irfft2(s, s=(sk, sk)) * np.float32((sk / size) ** 2))
            fields = np.stack(fields, axis=-1)
            if scale is None:   # unit standard deviation of each field at level 0
                scale = 1.0 / fields.reshape(-1, 3).std(axis=0)
            rgb = base + fields @ (scale[:, None] * mix).astype(np.float32)
            packed = np.zeros((sk, sk, 4), dtype=np.uint8)
            packed[..., :3] = np.clip(np.rint(rgb), 0, 255)
            self.levels.append(packed.view(np.uint32).reshape(-1))
            self.sizes.append(sk)

    def _lookup(self, k: int, tu: np.ndarray, tv: np.ndarray) -> np.ndarray:
        """(n, 4) float32 bilinear lookup of level k at level-0 coordinates (n,) float32 in
        [0, 2**20)."""
        s = self.sizes[k]
        x = tu * np.float32(0.5 ** k)
        y = tv * np.float32(0.5 ** k)
        ix = x.astype(np.int32)            # floor, as x >= 0
        iy = y.astype(np.int32)
        wx = (x - ix)[:, None]
        wy = (y - iy)[:, None]
        ix1 = (ix + 1) & (s - 1)
        ix &= s - 1
        r1 = ((iy + 1) & (s - 1)) * s
        r0 = (iy & (s - 1)) * s
        lev = self.levels[k]

        def rgba(idx):
            return lev[idx].view(np.uint8).reshape(-1, 4).astype(np.float32)

        c00 = rgba(r0 + ix)
        top = c00 + (rgba(r0 + ix1) - c00) * wx
        c10 = rgba(r1 + ix)
        bottom = c10 + (rgba(r1 + ix1) - c10) * wx
        return top + (bottom - top) * wy

    def _trilinear(self, tu: np.ndarray, tv: np.ndarray, level: np.ndarray) -> np.ndarray:
        """(n, 4) float32 lookup between the mip levels floor(level) and floor(level) + 1."""
        n_levels = len(self.sizes)
        k0 = level.astype(np.int64)
        frac = (level - k0).astype(np.float32)
        if k0.size and k0.min() == k0.max():
            groups = [(int(k0[0]), None)]
        else:
            groups = [(k, np.flatnonzero(k0 == k)) for k in range(k0.min(initial=0),
                                                                   k0.max(initial=-1) + 1)]
        out = np.empty((tu.shape[0], 4), dtype=np.float32)
        for k, sel in groups:
            su, sv, w = (tu, tv, frac) if sel is None else (tu[sel], tv[sel], frac[sel])
            if sel is not None and sel.size == 0:
                continue
            col = self._lookup(k, su, sv)
            if k + 1 < n_levels:
                blend = np.flatnonzero(w > 0)
                if blend.size:
                    upper = self._lookup(k + 1, su[blend], sv[blend])
                    col[blend] += (upper - col[blend]) * w[blend, None]
            if sel is None:
                out = col
            else:
                out[sel] = col
        return out

    def sample(self, tu: np.ndarray, tv: np.ndarray, jac: tuple) -> np.ndarray:
        """(n, 3) float32 RGB of pixels whose centres fall at level-0 texel coordinates tu, tv (n,)
        and whose texels-per-pixel Jacobian is ``jac`` = (du/dx, dv/dx, du/dy, dv/dy), each (n,).

        The filter keeps the texture's Gaussian cut-off wavelength at ``_MIN_WAVELENGTH_PX``
        pixels in every direction. With s1 >= s2 the semi-axes of the pixel footprint (singular
        values of the Jacobian, texels per pixel): where s1 <= ``_MIP_FOOTPRINT`` this is one
        bilinear lookup of level 0, independent of the view. Beyond, elliptical filtering: mip
        level of footprint l = max(s2, s1 / _MAX_ANISOTROPY, _MIP_FOOTPRINT) (trilinear),
        convolved along the major axis with the Gaussian that brings the cut-off from l to s1
        (taps at most _TAP_SPACING * l apart, within two standard deviations). The result varies
        continuously with the footprint.
        """
        dudx, dvdx, dudy, dvdy = jac
        a = dudx * dudx + dudy * dudy
        d = dvdx * dvdx + dvdy * dvdy
        b = dudx * dvdx + dudy * dvdy
        disc = np.sqrt((a - d) ** 2 + 4.0 * b * b)
        s1 = np.sqrt(0.5 * (a + d + disc))
        s2 = np.sqrt(np.maximum(0.5 * (a + d - disc), 0.0))
        ell = np.maximum(np.maximum(s2, s1 / _MAX_ANISOTROPY), _MIP_FOOTPRINT)
        level = np.minimum(np.log2(ell / _MIP_FOOTPRINT), len(self.sizes) - 1.0)
        # Gaussian exp(-(f L)^2) of cut-off wavelength L = _MIN_WAVELENGTH_PX * footprint: the
        # extra blur from l to s1 is a spatial Gaussian of this standard deviation, texels.
        sigma = (_MIN_WAVELENGTH_PX / (np.pi * np.sqrt(2.0))
                 * np.sqrt(np.maximum(s1 * s1 - ell * ell, 0.0)))
        half_taps = np.ceil(2.0 * sigma / (_TAP_SPACING * ell) - 1e-9).astype(np.int64)  # per side
        # Coordinates modulo the period plus a whole number of periods that keeps every tap
        # positive, in float32 (precise to 1e-4 texel where there are no taps).
        period = float(self.sizes[0])
        margin = period * np.ceil(2.0 * sigma / period + 1.0)
        tu = (np.mod(tu, period) + margin).astype(np.float32)
        tv = (np.mod(tv, period) + margin).astype(np.float32)
        out = np.empty((tu.shape[0], 4), dtype=np.float32)
        for m in np.unique(half_taps):
            sel = np.flatnonzero(half_taps == m)
            if m == 0:
                for c in range(0, sel.size, _CHUNK):
                    part = sel[c:c + _CHUNK]
                    out[part] = self._trilinear(tu[part], tv[part], level[part])
                continue
            phi = 0.5 * np.arctan2(2.0 * b[sel], a[sel] - d[sel])
            sg = sigma[sel]
            pos = np.arange(-m, m + 1, dtype=np.float64) / m * 2.0     # in standard deviations
            w = np.exp(-0.5 * pos ** 2)
            w = (w / w.sum()).astype(np.float32)
            off = (pos[:, None] * sg[None, :]).astype(np.float32)     # (taps, n) texels
            su = (tu[sel][None, :] + off * np.cos(phi).astype(np.float32)[None, :]).ravel()
            sv = (tv[sel][None, :] + off * np.sin(phi).astype(np.float32)[None, :]).ravel()
            lev = np.tile(level[sel], 2 * m + 1)
            taps = np.empty((su.size, 4), dtype=np.float32)
            for c in range(0, su.size, _CHUNK):   # chunks keep the temporaries in cache
                taps[c:c + _CHUNK] = self._trilinear(su[c:c + _CHUNK], sv[c:c + _CHUNK],
                                                     lev[c:c + _CHUNK])
            out[sel] = np.tensordot(w, taps.reshape(2 * m + 1, sel.size, 4), axes=1)
        return out[:, :3]


@lru_cache(maxsize=16)
def _texture(seed: int, index: int, size: int, rgb: tuple) -> _Texture:
    """Texture of material ``index`` of the scenes of ``seed``. Cached: the street and static-box
    materials of a seed are the same for every preset and size (at most 16, about 90 MB)."""
    rng = np.random.default_rng([seed, 4, index])
    return _Texture(rng, size, rgb, lum_std=_LUM_STD, chroma_std=_CHROMA_STD)


# ----------------------------------------------------------------------------------------------
# Boxes and ray casting


@dataclass
class _Box:
    """An oriented box: the street (seen from inside), a static box or a mover."""

    half: np.ndarray          # (3,) half extents along the box axes, metres
    R: np.ndarray             # (N, 3, 3) box-to-world rotation per frame
    centre: np.ndarray        # (N, 3) box centre in the world per frame, metres
    materials: tuple          # 6 material indices, one per face
    offsets: np.ndarray       # (6, 2) texture offsets per face, texels
    brightness: np.ndarray    # (6,) brightness factor per face
    inside: bool = False      # True for the street box, which the camera sees from inside
    mover: int = 0            # 0 static, k for mover k (1-based)
    kind: str = "street"      # street, crate, pillar, block, person, car

    def corners(self, i: int) -> np.ndarray:
        """(8, 3) world corners at frame i."""
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)],
                         dtype=np.float64)
        return (signs * self.half) @ self.R[i].T + self.centre[i]


@dataclass(frozen=True)
class _Grid:
    """Pixel-centre ray directions of one image size, in the camera frame with z = 1."""

    width: int
    height: int
    intr: Intrinsics
    a: np.ndarray = field(repr=False)   # (W,) (x - cx) / fx
    b: np.ndarray = field(repr=False)   # (H,) (y - cy) / fy

    @classmethod
    def make(cls, width: int, height: int, intr: Intrinsics) -> "_Grid":
        a = (np.arange(width, dtype=np.float64) - intr.cx) / intr.fx
        b = (np.arange(height, dtype=np.float64) - intr.cy) / intr.fy
        return cls(width, height, intr, a, b)


def _screen_rect(box: _Box, i: int, R_wc: np.ndarray, c: np.ndarray, grid: _Grid):
    """(y0, y1, x0, x1) pixel rectangle containing the box's image, or None when it is not seen."""
    if box.inside:
        return 0, grid.height, 0, grid.width
    pc = (box.corners(i) - c) @ R_wc
    z = pc[:, 2]
    if np.all(z <= 1e-6):
        return None
    if np.any(z <= 1e-6):
        return 0, grid.height, 0, grid.width
    x = grid.intr.fx * pc[:, 0] / z + grid.intr.cx
    y = grid.intr.fy * pc[:, 1] / z + grid.intr.cy
    x0 = max(int(np.floor(x.min())), 0)
    x1 = min(int(np.ceil(x.max())) + 1, grid.width)
    y0 = max(int(np.floor(y.min())), 0)
    y1 = min(int(np.ceil(y.max())) + 1, grid.height)
    if x0 >= x1 or y0 >= y1:
        return None
    return y0, y1, x0, x1


def _intersect(box: _Box, M: np.ndarray, o: np.ndarray, a: np.ndarray, b: np.ndarray):
    """Ray parameters (= camera z) and faces of rays d = M @ (a, b, 1) from o, in the box frame.

    a (w,), b (h,) are the pixel direction coordinates of a rectangle; returns t (h, w) float64
    (inf where missed) and face (h, w) int8.
    """
    lo, hi, d = [], [], []
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(3):
            dk = M[k, 0] * a[None, :] + (M[k, 1] * b + M[k, 2])[:, None]
            inv = 1.0 / dk
            t1 = (-box.half[k] - o[k]) * inv
            t2 = (box.half[k] - o[k]) * inv
            lo.append(np.minimum(t1, t2))
            hi.append(np.maximum(t1, t2))
            d.append(dk)
    if box.inside:
        t = np.minimum(np.minimum(hi[0], hi[1]), hi[2])
        ax = np.where((hi[0] <= hi[1]) & (hi[0] <= hi[2]), 0, np.where(hi[1] <= hi[2], 1, 2))
        d_ax = np.where(ax == 0, d[0], np.where(ax == 1, d[1], d[2]))
        face = (2 * ax + (d_ax > 0)).astype(np.int8)
        return t, face
    t_near = np.maximum(np.maximum(lo[0], lo[1]), lo[2])
    t_far = np.minimum(np.minimum(hi[0], hi[1]), hi[2])
    hit = (t_near <= t_far) & (t_near > 1e-9)
    ax = np.where((lo[0] >= lo[1]) & (lo[0] >= lo[2]), 0, np.where(lo[1] >= lo[2], 1, 2))
    d_ax = np.where(ax == 0, d[0], np.where(ax == 1, d[1], d[2]))
    face = (2 * ax + (d_ax < 0)).astype(np.int8)
    return np.where(hit, t_near, np.inf), face


def _trace(boxes: Sequence[_Box], i: int, R_wc: np.ndarray, c: np.ndarray, grid: _Grid):
    """Nearest hits of all pixel rays of frame i: t (H, W) float64 camera z, metres (inf where no
    box is hit), box index (H, W) int16 (-1 where none) and face (H, W) int8."""
    t_best = np.full((grid.height, grid.width), np.inf)
    box_best = np.full((grid.height, grid.width), -1, dtype=np.int16)
    face_best = np.zeros((grid.height, grid.width), dtype=np.int8)
    for n, box in enumerate(boxes):
        rect = _screen_rect(box, i, R_wc, c, grid)
        if rect is None:
            continue
        y0, y1, x0, x1 = rect
        Rb = box.R[i]
        M = Rb.T @ R_wc
        o = Rb.T @ (c - box.centre[i])
        t, face = _intersect(box, M, o, grid.a[x0:x1], grid.b[y0:y1])
        sub_t = t_best[y0:y1, x0:x1]
        better = t < sub_t
        sub_t[better] = t[better]
        box_best[y0:y1, x0:x1][better] = n
        face_best[y0:y1, x0:x1][better] = face[better]
    return t_best, box_best, face_best


# ----------------------------------------------------------------------------------------------
# The scene


@dataclass
class _MoverProposal:
    kind: str
    half: np.ndarray      # (3,) half extents, metres
    xz: np.ndarray        # (N, 2) ground position per frame, metres
    heading: np.ndarray   # (N,) radians, direction (sin, cos) in (x, z)


class SyntheticScene:
    """A rendered-on-demand synthetic sequence with exact ground truth (see the module docstring).

    ``len(scene)`` frames; iterate for lazily rendered :class:`RenderedFrame` objects.
    """

    def __init__(self, config: SceneConfig | None = None):
        self.config = config if config is not None else SceneConfig()
        cfg = self.config
        n = cfg.n_frames
        fast = cfg.preset == "fast-rotation"

        rng = np.random.default_rng([cfg.seed, 1])
        hfov = np.radians(rng.uniform(55.0, 75.0) if cfg.hfov_deg is None else cfg.hfov_deg)
        f = 0.5 * cfg.width / np.tan(hfov / 2.0)
        pp = rng.uniform(-0.02, 0.02, 2)
        self.intrinsics = Intrinsics(float(f), float(f),
                                     float((cfg.width - 1) / 2.0 + pp[0] * cfg.width),
                                     float((cfg.height - 1) / 2.0 + pp[1] * cfg.height))
        self._hfov = float(hfov)
        self._R_wc, self._centres, self._yaw = self._camera_path(rng, n, fast)
        self._poses = np.stack([make_pose(R, c) for R, c in zip(self._R_wc, self._centres)])

        rng = np.random.default_rng([cfg.seed, 2])
        self._boxes: list[_Box] = [self._street(rng)]
        self._boxes += self._static_boxes(rng)
        self.n_static = len(self._boxes) - 1

        gw = _COVERAGE_GRID_WIDTH
        gh = max(int(round(gw * cfg.height / cfg.width)), 8)
        self._coverage_grid = _Grid.make(gw, gh, self.intrinsics.scaled(gw / cfg.width,
                                                                        gh / cfg.height))
        rng = np.random.default_rng([cfg.seed, 3, list(PRESETS).index(cfg.preset)])
        self._boxes += self._movers(rng)
        self.n_movers = len(self._boxes) - 1 - self.n_static
        self.mover_kinds = tuple(b.kind for b in self._boxes if b.mover)
        self._grid = _Grid.make(cfg.width, cfg.height, self.intrinsics)

    # -- public API ---------------------------------------------------------------------------

    def __len__(self) -> int:
        return self.config.n_frames

    def __iter__(self) -> Iterator[RenderedFrame]:
        for i in range(len(self)):
            yield self.render(i)

    def poses(self) -> np.ndarray:
        """(N, 4, 4) float64 T_world_cam of all frames (a copy)."""
        return self._poses.copy()

    def path_length(self) -> float:
        """Sum of the camera centre steps between consecutive frames, metres."""
        return float(np.linalg.norm(np.diff(self._centres, axis=0), axis=1).sum())

    def coverage(self) -> np.ndarray:
        """(N,) float64 fraction of the pixels showing a mover in each frame (exactly the rendered
        masks' means; geometry only, no texturing)."""
        return self._coverage.copy()

    @cached_property
    def _coverage(self) -> np.ndarray:
        n_static = self.n_static
        out = np.zeros(len(self))
        if self.n_movers == 0:
            return out
        for i in range(len(self)):
            _, box, _ = _trace(self._boxes, i, self._R_wc[i], self._centres[i], self._grid)
            out[i] = np.mean(box > n_static)
        return out

    def render(self, i: int) -> RenderedFrame:
        """Frame i (0 <= i < len(scene)) with its ground truth."""
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} out of range 0..{len(self) - 1}")
        grid = self._grid
        R_wc, c = self._R_wc[i], self._centres[i]
        t, box, face = _trace(self._boxes, i, R_wc, c, grid)
        face_id = (box.astype(np.int16) * 6 + face).astype(np.int16)
        image = self._shade(i, t, face_id)
        mover_of_box = np.array([b.mover for b in self._boxes], dtype=np.uint8)
        object_id = mover_of_box[box]
        return RenderedFrame(index=i, image=image, depth=t.astype(np.float32),
                             mask=object_id > 0, object_id=object_id, face_id=face_id,
                             T_world_cam=self._poses[i].copy(), intrinsics=self.intrinsics)

    # -- shading ------------------------------------------------------------------------------

    @cached_property
    def _textures(self) -> list[_Texture]:
        return [_texture(self.config.seed, m, size, rgb)
                for m, (size, _, rgb) in enumerate(self._materials)]

    def _shade(self, i: int, t: np.ndarray, face_id: np.ndarray) -> np.ndarray:
        grid = self._grid
        intr = grid.intr
        R_wc, c = self._R_wc[i], self._centres[i]
        H, W = t.shape
        flat_id = face_id.ravel()
        flat_t = t.ravel()
        order = np.argsort(flat_id, kind="stable")
        keys = flat_id[order]
        cuts = np.flatnonzero(np.diff(keys)) + 1
        image = np.empty((H * W, 3), dtype=np.float32)
        textures = self._textures
        for start, stop in zip(np.r_[0, cuts], np.r_[cuts, keys.size]):
            idx = order[start:stop]
            key = int(keys[start])
            box = self._boxes[key // 6]
            fc = key % 6
            ax = fc // 2
            ua, va = _UV_AXES[ax]
            Rb = box.R[i]
            M = Rb.T @ R_wc
            o = Rb.T @ (c - box.centre[i])
            a = grid.a[idx % W]
            b = grid.b[idx // W]
            tt = flat_t[idx]
            d = [M[k, 0] * a + M[k, 1] * b + M[k, 2] for k in range(3)]
            u = o[ua] + tt * d[ua] + box.half[ua]
            v = o[va] + tt * d[va] + box.half[va]
            # Pixel footprint on the face: dX/dpx = t/fx (r_x - d (n.r_x)/(n.d)), r_x = M[:, 0]
            # (camera x axis in the box frame), likewise for y; in texels per pixel.
            tex = textures[box.materials[fc]]
            tpm = self._materials[box.materials[fc]][1]
            sx = (tt / intr.fx) * tpm
            sy = (tt / intr.fy) * tpm
            ratio_x = M[ax, 0] / d[ax]
            ratio_y = M[ax, 1] / d[ax]
            jac = ((M[ua, 0] - d[ua] * ratio_x) * sx, (M[va, 0] - d[va] * ratio_x) * sx,
                   (M[ua, 1] - d[ua] * ratio_y) * sy, (M[va, 1] - d[va] * ratio_y) * sy)
            col = tex.sample(u * tpm + box.offsets[fc, 0], v * tpm + box.offsets[fc, 1], jac)
            image[idx] = col * np.float32(box.brightness[fc])
        return np.clip(np.rint(image), 0, 255).astype(np.uint8).reshape(H, W, 3)

    # -- construction -------------------------------------------------------------------------

    @staticmethod
    def _camera_path(rng, n: int, fast: bool):
        """Rotations (N, 3, 3), centres (N, 3) and yaw (N,) of a smooth camera path."""
        t = np.arange(n, dtype=np.float64)
        deg = np.pi / 180.0
        speed = rng.uniform(0.03, 0.08) if fast else rng.uniform(0.05, 0.25)   # m/frame
        z = speed * t + _waves(rng, t, 0.25 * speed, (30.0, 90.0))
        sway = rng.uniform(0.01, 0.04) if fast else rng.uniform(0.02, 0.08)   # m/frame peak
        x = rng.uniform(-1.0, 1.0) + _waves(rng, t, sway, (40.0, 120.0), max_amplitude=1.5)
        y = -rng.uniform(1.4, 1.8) + _waves(rng, t, rng.uniform(0.003, 0.01), (20.0, 60.0))
        # Peak rates, degrees per frame, and the period range of the main yaw wave, frames.
        if fast:
            yaw_rate, pitch_rate, yaw_period = rng.uniform(4, 6), rng.uniform(2, 3), (40, 70)
        else:
            yaw_rate, pitch_rate = rng.uniform(0.3, 0.8), rng.uniform(0.1, 0.3)
            yaw_period = (40, 120)
        yaw = (rng.uniform(-10.0, 10.0) * deg + _waves(rng, t, yaw_rate * deg, yaw_period)
               + _waves(rng, t, rng.uniform(0.1, 0.3) * deg, (15.0, 40.0)))
        pitch = (rng.uniform(-6.0, 3.0) * deg
                 + _waves(rng, t, pitch_rate * deg, (25.0, 50.0) if fast else (30.0, 90.0)))
        roll = rng.uniform(-2.0, 2.0) * deg + _waves(rng, t, rng.uniform(0.05, 0.2) * deg,
                                                     (30.0, 90.0))
        R = np.stack([_rot_y(a) @ _rot_x(p) @ _rot_z(r) for a, p, r in zip(yaw, pitch, roll)])
        return R, np.stack([x, y, z], axis=1), yaw

    def _material(self, size: int, density: float, rgb) -> int:
        """A new material: texture size, texels per metre = density * fx, base colour RGB."""
        self._materials.append((size, density * self.intrinsics.fx, tuple(int(v) for v in rgb)))
        return len(self._materials) - 1

    def _street(self, rng) -> _Box:
        n = self.config.n_frames
        zc = self._centres[:, 2]
        width = rng.uniform(12.0, 16.0)
        height = rng.uniform(7.0, 9.0)
        z0 = zc.min() - rng.uniform(4.0, 7.0)
        z1 = zc.max() + rng.uniform(25.0, 35.0)
        self._street_extent = (width, height, z0, z1)
        self._materials: list[tuple] = []
        walls = rng.choice(len(_WORLD_COLOURS), 4, replace=False)
        jitter = rng.uniform(-8, 8, (4, 3))
        colours = [np.add(_WORLD_COLOURS[k], j) for k, j in zip(walls, jitter)]
        left = self._material(1024, _STREET_DENSITY, colours[0])
        right = self._material(1024, _STREET_DENSITY, colours[1])
        floor = self._material(1024, _STREET_DENSITY, colours[2] * 0.85)
        ends = self._material(1024, _STREET_DENSITY, colours[3])
        sky = self._material(1024, _SKY_DENSITY, _SKY_COLOUR)
        # Faces: -x left wall, +x right wall, -y sky (up), +y floor, -z back, +z front.
        brightness = np.array([0.92, 0.86, 1.0, 0.9, 0.9, 0.95]) + rng.uniform(-0.03, 0.03, 6)
        return _Box(half=np.array([width / 2.0, height / 2.0, (z1 - z0) / 2.0]),
                    R=np.broadcast_to(np.eye(3), (n, 3, 3)),
                    centre=np.broadcast_to([0.0, -height / 2.0, (z0 + z1) / 2.0], (n, 3)),
                    materials=(left, right, sky, floor, ends, ends),
                    offsets=rng.uniform(0.0, 1024.0, (6, 2)), brightness=brightness,
                    inside=True, kind="street")

    def _box_brightness(self, rng) -> np.ndarray:
        # -x, +x, top (-y), bottom (+y), -z, +z: a fixed fake light from above and one side.
        return np.array([0.82, 0.95, 1.0, 0.6, 0.88, 0.76]) + rng.uniform(-0.04, 0.04, 6)

    def _static_boxes(self, rng) -> list[_Box]:
        n = self.config.n_frames
        width, height, z0, z1 = self._street_extent
        mats = [self._material(512, _STATIC_DENSITY,
                               np.add(_STATIC_COLOURS[k], rng.uniform(-8, 8, 3)))
                for k in rng.choice(len(_STATIC_COLOURS), 3, replace=False)]
        cam_xz = self._centres[:, [0, 2]]
        placed: list[np.ndarray] = []
        boxes = []
        n_target = int(rng.integers(6, 11))
        for _ in range(200):
            if len(boxes) == n_target:
                break
            kind = rng.choice(["crate", "crate", "pillar", "block"])
            if kind == "crate":
                size = rng.uniform([0.5, 0.5, 0.5], [1.4, 1.3, 1.4])
            elif kind == "pillar":
                s = rng.uniform(0.4, 0.8)
                size = np.array([s, rng.uniform(3.0, height - 0.5), s])
            else:
                size = rng.uniform([1.5, 1.2, 1.5], [3.0, 2.6, 3.0])
            half = size / 2.0
            near_wall = rng.random() < 0.6
            side = rng.choice([-1.0, 1.0])
            x = side * (width / 2.0 - rng.uniform(0.1, 2.5) - half.max() * 1.5) if near_wall \
                else rng.uniform(-width / 2.0 + 1.0, width / 2.0 - 1.0)
            z = rng.uniform(z0 + 1.0, z1 - 1.0)
            yaw = rng.uniform(-np.pi, np.pi)
            corners = _footprint_corners(np.array([[x, z]]), np.array([yaw]), half[[0, 2]])[0]
            if (np.any(np.abs(corners[:, 0]) > width / 2.0 - 0.05)
                    or np.any(corners[:, 1] < z0 + 0.05) or np.any(corners[:, 1] > z1 - 0.05)):
                continue
            R = _rot_y(yaw)
            centre = np.array([x, -half[1], z])
            cam3 = np.column_stack([cam_xz[:, 0], np.full(n, centre[1]), cam_xz[:, 1]])
            dist = _point_box_distance(cam3, np.broadcast_to(R, (n, 3, 3)),
                                       np.broadcast_to(centre, (n, 3)), half)
            if dist.min() < _STATIC_CLEARANCE:
                continue
            if any(_footprints_overlap(corners[None], other[None])[0] for other in placed):
                continue
            placed.append(corners)
            mat = mats[0] if kind == "crate" else mats[1] if kind == "pillar" else mats[2]
            boxes.append(_Box(half=half, R=np.broadcast_to(R, (n, 3, 3)),
                              centre=np.broadcast_to(centre, (n, 3)), materials=(mat,) * 6,
                              offsets=rng.uniform(0.0, 512.0, (6, 2)),
                              brightness=self._box_brightness(rng), kind=str(kind)))
        self._static_footprints = placed
        return boxes

    # -- movers -------------------------------------------------------------------------------

    def _movers(self, rng) -> list[_Box]:
        preset = self.config.preset
        if preset == "static":
            return []
        if preset == "several":
            count = int(rng.integers(2, 4))
        else:
            count = 1
        accepted: list[_MoverProposal] = []
        covs: list[np.ndarray] = []
        car_used = False
        for m in range(count):
            for attempt in range(_MAX_TRIES):
                prop = self._propose(rng, allow_car=not car_used)
                cov = self._check(prop, accepted, covs)
                if cov is not None:
                    log.debug("mover %d (%s) accepted after %d proposals", m + 1, prop.kind,
                              attempt + 1)
                    accepted.append(prop)
                    covs.append(cov)
                    car_used |= prop.kind == "car"
                    break
            else:
                if preset == "several" and m >= 2:
                    log.debug("third mover could not be placed; keeping two")
                    break
                cfg = self.config
                raise MonaVoError(
                    f"synthetic scene: could not place mover {m + 1} of preset {preset!r} for "
                    f"seed {cfg.seed} and {cfg.n_frames} frames in {_MAX_TRIES} tries; "
                    f"use another seed or fewer frames")
        colours = rng.permutation(min(len(_CAR_COLOURS), len(_PERSON_COLOURS)))  # all distinct
        return [self._mover_box(rng, prop, k + 1, int(colours[k]))
                for k, prop in enumerate(accepted)]

    def _propose(self, rng, allow_car: bool) -> _MoverProposal:
        """A random mover trajectory anchored in front of the camera at a mid-sequence frame."""
        preset = self.config.preset
        n = self.config.n_frames
        deg = np.pi / 180.0
        p_car = {"one-large": 0.55, "several": 0.35, "fast-rotation": 0.4}[preset]
        kind = "car" if (allow_car and rng.random() < p_car) else "person"
        if kind == "car":
            size = rng.uniform([1.7, 1.4, 3.9], [1.95, 1.6, 4.7])
            dist = {"one-large": (4.5, 8.5), "several": (5.0, 15.0),
                    "fast-rotation": (5.0, 10.0)}[preset]
        else:
            size = rng.uniform([0.45, 1.6, 0.28], [0.6, 1.9, 0.4])
            dist = {"one-large": (1.8, 3.2), "several": (2.5, 10.0),
                    "fast-rotation": (2.0, 5.0)}[preset]
        cam_speed = np.linalg.norm(np.diff(self._centres[:, [0, 2]], axis=0), axis=1).mean()
        p_follow = 0.5 if preset == "one-large" else 0.15
        scenario = rng.choice(["follow", "along", "crossing", "oncoming"],
                              p=[p_follow, 0.55 - p_follow / 2, 0.3 - p_follow / 2, 0.15])
        if scenario == "follow" and kind == "person" and cam_speed > 0.06:
            scenario = "along"       # nobody walks that fast
        spread = 0.15 if scenario == "follow" else 0.3 if preset == "one-large" else 0.45
        bearing = rng.uniform(-spread, spread) * self._hfov
        anchor = int(round(rng.uniform(0.3, 0.7) * (n - 1)))
        d = rng.uniform(*dist)
        cam_yaw = self._yaw[anchor]
        xz_anchor = self._centres[anchor, [0, 2]] + d * np.array(
            [np.sin(cam_yaw + bearing), np.cos(cam_yaw + bearing)])
        sub = 8                                  # time steps per frame of the fine grid
        tf = np.arange((n - 1) * sub + 1, dtype=np.float64) / sub
        if scenario == "follow":
            # Keeps the camera's pace down the street (z) at a varying distance, weaving across.
            x = xz_anchor[0] + _waves(rng, tf, rng.uniform(0.0, 0.02), (30.0, 90.0))
            z = (np.interp(tf, np.arange(n), self._centres[:, 2]) - self._centres[anchor, 2]
                 + xz_anchor[1] + _waves(rng, tf, rng.uniform(0.0, 0.03), (30.0, 90.0)))
            pos = np.stack([x, z], axis=1)
            vel = np.gradient(pos, tf, axis=0)
            heading = np.arctan2(vel[:, 0], vel[:, 1])
            pos = pos - pos[anchor * sub] + xz_anchor
            return _MoverProposal(kind=kind, half=size / 2.0, xz=pos[::sub].copy(),
                                  heading=heading[::sub].copy())
        if scenario == "along":
            rel = rng.uniform(-25.0, 25.0) * deg
            speed = (cam_speed * rng.uniform(0.7, 1.3) if kind == "car"
                     else rng.uniform(0.025, 0.06))
            speed = max(speed, 0.04 if kind == "car" else 0.025)
        elif scenario == "crossing":
            rel = rng.choice([-1.0, 1.0]) * rng.uniform(60.0, 120.0) * deg
            speed = rng.uniform(0.04, 0.12) if kind == "car" else rng.uniform(0.025, 0.05)
        else:
            rel = np.pi + rng.uniform(-20.0, 20.0) * deg
            speed = rng.uniform(0.05, 0.15) if kind == "car" else rng.uniform(0.025, 0.05)
        turn = rng.uniform(-1.0, 1.0) * deg if kind == "car" else rng.uniform(-2.0, 2.0) * deg
        # Heading and speed on the fine grid, integrated to positions, anchored at `anchor`.
        heading = cam_yaw + rel + turn * (tf - anchor)
        heading = heading + _waves(rng, tf, rng.uniform(0.0, 1.0) * deg, (20.0, 60.0))
        spd = speed * (1.0 + 0.15 * np.sin(2 * np.pi * tf / rng.uniform(20, 60)
                                          + rng.uniform(0, 2 * np.pi)))
        vel = spd[:, None] * np.stack([np.sin(heading), np.cos(heading)], axis=1)
        pos = np.concatenate([[[0.0, 0.0]], np.cumsum(0.5 * (vel[1:] + vel[:-1]) / sub, axis=0)])
        pos = pos[::sub]
        pos = pos - pos[anchor] + xz_anchor
        return _MoverProposal(kind=kind, half=size / 2.0, xz=pos, heading=heading[::sub].copy())

    def _check(self, prop: _MoverProposal, accepted, covs) -> np.ndarray | None:
        """The proposal's per-frame coverage on the coarse grid when it is admissible, else None."""
        n = self.config.n_frames
        width, height, z0, z1 = self._street_extent
        half_xz = prop.half[[0, 2]]
        corners = _footprint_corners(prop.xz, prop.heading, half_xz)
        lim = width / 2.0 - _GAP
        if (np.any(np.abs(corners[..., 0]) > lim) or np.any(corners[..., 1] < z0 + _GAP)
                or np.any(corners[..., 1] > z1 - _GAP)):
            return None
        R = np.stack([_rot_y(h) for h in prop.heading])
        centre = np.column_stack([prop.xz[:, 0], np.full(n, -prop.half[1]), prop.xz[:, 1]])
        if _point_box_distance(self._centres, R, centre, prop.half).min() < _CAMERA_CLEARANCE:
            return None
        grown = _footprint_corners(prop.xz, prop.heading, half_xz + _GAP)
        for other in self._static_footprints:
            if np.any(_footprints_overlap(grown, np.broadcast_to(other, grown.shape))):
                return None
        for other in accepted:
            oc = _footprint_corners(other.xz, other.heading, other.half[[0, 2]])
            if np.any(_footprints_overlap(grown, oc)):
                return None
        box = _Box(half=prop.half, R=R, centre=centre, materials=(0,) * 6,
                   offsets=np.zeros((6, 2)), brightness=np.ones(6), mover=1, kind=prop.kind)
        preset = self.config.preset
        boxes = self._boxes[1:] + [box]
        # Coarse coverage, checking every 4th frame first to reject quickly.
        cov = np.full(n, np.nan)
        order = list(range(0, n, 4)) + [i for i in range(n) if i % 4]
        for count, i in enumerate(order):
            _, hit, _ = _trace(boxes, i, self._R_wc[i], self._centres[i], self._coverage_grid)
            cov[i] = np.mean(hit == len(boxes) - 1)
            if count == (n + 3) // 4 - 1 or count == n - 1:
                done = cov[~np.isnan(cov)]
                if not self._coverage_ok(preset, done, covs, ~np.isnan(cov)):
                    return None
        return cov

    @staticmethod
    def _coverage_ok(preset, cov, others, sel) -> bool:
        total = cov + sum(o[sel] for o in others)
        if np.any(total > _MAX_COVERAGE):
            return False
        visible = cov > _VISIBLE_COVERAGE
        if preset == "one-large":
            lo, hi = _ONE_LARGE_RANGE
            return bool(np.all(visible) and np.mean((cov >= lo) & (cov <= hi))
                        >= _ONE_LARGE_IN_RANGE)
        if preset == "several":
            return bool(np.mean(visible) >= _SEVERAL_VISIBLE_FRAMES and cov.max() < 0.3)
        return bool(np.mean(visible) >= _FAST_VISIBLE_FRAMES)

    def _mover_box(self, rng, prop: _MoverProposal, k: int, colour: int) -> _Box:
        n = self.config.n_frames
        palette = _CAR_COLOURS if prop.kind == "car" else _PERSON_COLOURS
        rgb = np.add(palette[colour], rng.uniform(-10, 10, 3))
        mat = self._material(1024, _MOVER_DENSITY, rgb)
        R = np.stack([_rot_y(h) for h in prop.heading])
        centre = np.column_stack([prop.xz[:, 0], np.full(n, -prop.half[1]), prop.xz[:, 1]])
        return _Box(half=prop.half, R=R, centre=centre, materials=(mat,) * 6,
                    offsets=rng.uniform(0.0, 1024.0, (6, 2)),
                    brightness=self._box_brightness(rng), mover=k, kind=prop.kind)


# ----------------------------------------------------------------------------------------------
# Writers


def _write_png(path: Path, image: np.ndarray) -> None:
    """Atomic PNG write; image (H, W, 3) uint8 RGB or (H, W) uint8."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), image):
            raise MonaVoError(f"{path}: cv2.imwrite failed")


def write_sintel(scene: SyntheticScene, root, seq: str = "synthetic",
                 passes: Sequence[str] = ("clean", "final")) -> Path:
    """Write ``scene`` in MPI Sintel's layout under ``root`` and return ``root``.

    ``root/training/<pass>/<seq>/frame_%04d.png`` (numbered from 1; every pass gets the same
    image: there is no blur or fog), ``root/training/camdata_left/<seq>/frame_%04d.cam``,
    ``root/training/depth/<seq>/frame_%04d.dpt`` and ``root/training/moving_masks/<seq>/
    frame_%04d.png`` (8-bit, 255 on movers, 0 elsewhere). Each file is written atomically.
    """
    root = Path(root)
    train = root / "training"
    for frame in scene:
        name = f"frame_{frame.index + 1:04d}"
        for p in passes:
            _write_png(train / p / seq / f"{name}.png", frame.image)
        write_cam(train / "camdata_left" / seq / f"{name}.cam", frame.intrinsics, frame.T_world_cam)
        write_dpt(train / "depth" / seq / f"{name}.dpt", frame.depth)
        _write_png(train / "moving_masks" / seq / f"{name}.png",
                   frame.mask.astype(np.uint8) * 255)
    return root


def write_frames_folder(scene: SyntheticScene, folder) -> Path:
    """Write ``scene`` as a plain frame folder and return it.

    ``folder/%05d.png`` (frame numbers from 0), ``folder/masks/%05d.png`` (0/255),
    ``folder/groundtruth.txt`` (TUM: ``timestamp tx ty tz qx qy qz qw`` with timestamp = frame
    number, T_world_cam) and ``folder/calib.txt`` (one line ``fx fy cx cy``, pixels).
    """
    folder = Path(folder)
    lines = []
    for frame in scene:
        _write_png(folder / f"{frame.index:05d}.png", frame.image)
        _write_png(folder / "masks" / f"{frame.index:05d}.png", frame.mask.astype(np.uint8) * 255)
        lines.append(" ".join(repr(float(v)) for v in tum_row(frame.index, frame.T_world_cam)))
    write_text_atomic(folder / "groundtruth.txt", "\n".join(lines) + "\n")
    k = scene.intrinsics
    write_text_atomic(folder / "calib.txt", f"{k.fx!r} {k.fy!r} {k.cx!r} {k.cy!r}\n")
    return folder


def write_video(scene: SyntheticScene, path, fps: float = 24.0) -> Path:
    """Write the frames of ``scene`` as an mp4 video (codec mp4v, ``fps`` frames per second)."""
    path = Path(path)
    cfg = scene.config
    with atomic_path(path) as tmp:
        writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps),
                                 (cfg.width, cfg.height))
        if not writer.isOpened():
            raise MonaVoError(f"{path}: cv2.VideoWriter cannot write mp4v video")
        try:
            for frame in scene:
                writer.write(cv2.cvtColor(frame.image, cv2.COLOR_RGB2BGR))
        finally:
            writer.release()
    return path
