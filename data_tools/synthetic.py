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
    m/frame. Intrinsics: fx = fy from a field of view of 55-75 deg across the longer side (a
    portrait frame is a landscape camera turned, as on a phone), principal point within 2 % of the
    image centre, constant over the sequence. The camera, street and static boxes
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

Newer presets (creep, pan, mixed)
    The legacy presets above keep their draws, so a seed renders the same pixels as before (the
    tests pin checksums). The newer ones draw a *recipe* first (:func:`draw_recipe`, stream
    ``[seed, 6, preset]``): a camera path from :data:`CAMERA_PATHS`, movers as (kind, behaviour)
    and image effects. ``creep`` creeps about 1 cm/frame (0.8-1.2 cm, rotation jitter below 0.3
    deg/frame) in a room whose end wall is 10-18 m ahead, static boxes kept 3.5 m from the path;
    ``pan`` turns 0.5-2 deg/frame about a centre that never moves; ``mixed`` cycles its camera
    path with the seed (any 8 consecutive seeds hold all 8 paths), draws the field of view in
    40-90 deg and, per material, a texture style (1/f-like noise of slope 0.85-1.15, a
    low-texture surface of 1.5-5 grey levels, or bricks, tiles or stripes), 1-3 movers and each
    effect with its own probability. Movers of the newer presets are articulated: a person is
    legs, arms, torso and head, its legs and arms swinging with the distance walked (and with
    time for slow movers); an animal has four swinging legs; a car is a body and a cabin. All
    parts of mover k carry id k. Behaviours: along, crossing, oncoming, follow (keeps the
    camera's pace), slow (3-15 mm/frame), enter-leave (visible on 20-85 % of the frames, absent at
    the start or the end) and cross-pair (two movers at different depths whose images cross).
    Effects (on ``RenderedFrame.image``; ``image_clean`` is without them): motion blur (the image
    averaged along each pixel's exact motion over a shutter of 0.3-0.9 frame), exposure gain
    (exp of a sinusoid of amplitude 0.1-0.3), Gaussian plus shot noise (sigma 1-4 grey levels),
    JPEG (quality 35-90). Depth, masks and ids are geometric and never touched by the effects:
    the mask is where a mover is rendered (blur can smear its colour a pixel or two beyond it).
    Textures of the newer presets scale with fx (same period in metres at any image size).
"""
from __future__ import annotations

import functools
import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from pathlib import Path

import cv2
import numpy as np

from data_tools.atomic import atomic_path, write_text_atomic
from data_tools.sintel_formats import write_cam, write_dpt
from mona_vo.conventions import (Intrinsics, fov_span, make_pose, relative_pose,
                                 rotation_angle_deg, tum_row)
from mona_vo.errors import ConfigError, MonaVoError

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
    "creep": "slow hand-held creep: about 1 cm of translation per frame with small hand-held "
             "rotation jitter, background 4-20 m away, one walking person (articulated)",
    "pan": "pure rotation about the camera centre (tripod pan, 0.5-2 deg/frame, no translation "
           "at all), one mover",
    "mixed": "per seed, a draw from everything: 40-90 deg field of view, natural-image textures "
             "(1/f spectra, low-texture and repetitive surfaces), a camera path from "
             "CAMERA_PATHS, 1-3 movers (articulated people and animals, cars, slow movers, "
             "movers entering and leaving, two movers crossing), image effects (motion blur, "
             "noise, exposure change, JPEG) on the final image",
}

# Presets whose pixels are pinned for a seed (tests checksum them): their draws never change.
LEGACY_PRESETS = ("static", "one-large", "several", "fast-rotation")

# Camera paths of the newer presets; ``mixed`` draws one per seed (or takes SceneConfig.camera_path).
CAMERA_PATHS: dict[str, str] = {
    "street-walk": "the street path of the legacy presets: 0.05-0.25 m/frame, yaw 0.3-0.8 deg/frame",
    "fast-rotation": "the fast-rotation path: yaw peaks 4-6 deg/frame, forward 0.03-0.08 m/frame",
    "handheld": "slow walk 0.01-0.04 m/frame with hand-held shake (0.15-0.5 deg/frame jitter)",
    "follow": "walking behind a mover at its pace (0.025-0.05 m/frame); the first mover keeps "
              "pace ahead of the camera",
    "pan": "pure rotation about a fixed centre, 0.5-2 deg/frame, no translation",
    "slow-pan": "slow pan 0.2-0.6 deg/frame while drifting sideways 0.3-1.5 cm/frame",
    "forward": "driving forward 0.2-0.45 m/frame at 1.2-1.6 m height, little rotation",
    "creep": "slow hand-held creep, about 1 cm/frame, small rotation jitter",
}
MOVER_BEHAVIOURS = ("along", "crossing", "oncoming", "follow", "slow", "enter-leave", "cross-pair")
EFFECTS = ("motion_blur", "noise", "exposure", "jpeg")

# Coverage rules of the presets, on the coarse grid used while placing movers.
_ONE_LARGE_RANGE = (0.16, 0.44)      # fraction of the image; a little inside 15-45 % for the grid
_ONE_LARGE_IN_RANGE = 0.85           # fraction of frames whose coverage must be in that range
_MAX_COVERAGE = 0.46                 # fraction of the image, any frame, all movers together
_VISIBLE_COVERAGE = 0.002            # fraction of the image above which a mover counts as visible
_SEVERAL_VISIBLE_FRAMES = 0.7        # fraction of frames showing each mover of "several"
_FAST_VISIBLE_FRAMES = 0.5           # same for the mover of "fast-rotation"
_MAX_TRIES = 400                     # proposals per mover before giving up
_COVERAGE_GRID_WIDTH = 128           # pixels across of the coarse coverage grid
_SHUTTER_BAND_ROWS = 4               # rows rendered at one instant under a rolling shutter

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


class SceneConfigError(ConfigError, ValueError):
    """A :class:`SceneConfig` field is wrong; the message names the key (one line)."""


def _is_int(v) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))


@dataclass(frozen=True)
class SceneConfig:
    """What to render. Every field has a default and is checked when the config is made (one-line
    :class:`SceneConfigError`, a ``ValueError``, naming the key)."""

    width: int = 1024               # image width, pixels (16-8192)
    height: int = 436               # image height, pixels (16-8192)
    n_frames: int = 50              # number of frames (2-100000)
    preset: str = "one-large"       # scene kind, a name in PRESETS
    seed: int = 0                   # seed of every random choice (non-negative integer)
    hfov_deg: float | None = None   # field of view across the longer side, degrees [10, 150];
    #                                 None: drawn (55-75 deg, mixed 40-90 deg)
    camera_path: str | None = None  # mixed only: a name in CAMERA_PATHS; None: drawn per seed
    effects: bool = True            # mixed only: image effects on RenderedFrame.image (False: none)
    readout: float = 0.0            # rolling shutter: the share of the frame interval [0, 1] the
    #                                 rows take to be read, top row first; 0: a global shutter

    def __post_init__(self):
        def bad(key, msg):
            raise SceneConfigError(f"SceneConfig.{key}: {msg}")

        if not isinstance(self.preset, str) or self.preset not in PRESETS:
            bad("preset", f"unknown preset {self.preset!r}; valid presets: {', '.join(PRESETS)}")
        for key, lo, hi in (("width", 16, 8192), ("height", 16, 8192), ("n_frames", 2, 100000)):
            v = getattr(self, key)
            if not _is_int(v):
                bad(key, f"must be an integer, got {v!r}")
            if not lo <= v <= hi:
                bad(key, f"must be in [{lo}, {hi}], got {v}")
        if not (_is_int(self.seed) and self.seed >= 0):
            bad("seed", f"must be a non-negative integer, got {self.seed!r}")
        if self.hfov_deg is not None:
            if (isinstance(self.hfov_deg, (bool, np.bool_))
                    or not isinstance(self.hfov_deg, (int, float, np.integer, np.floating))
                    or not 10.0 <= float(self.hfov_deg) <= 150.0):
                bad("hfov_deg", f"must be None or a number in [10, 150] degrees, "
                                f"got {self.hfov_deg!r}")
        if self.camera_path is not None:
            if self.preset != "mixed":
                bad("camera_path", f"only the mixed preset takes a camera path (preset "
                                   f"{self.preset!r} has its own); leave it None")
            if self.camera_path not in CAMERA_PATHS:
                bad("camera_path", f"unknown camera path {self.camera_path!r}; valid: "
                                   f"{', '.join(CAMERA_PATHS)}")
        if not isinstance(self.effects, (bool, np.bool_)):
            bad("effects", f"must be true or false, got {self.effects!r}")
        if (isinstance(self.readout, (bool, np.bool_))
                or not isinstance(self.readout, (int, float, np.integer, np.floating))
                or not 0.0 <= float(self.readout) <= 1.0):
            bad("readout", f"must be a number in [0, 1] (a share of the frame interval), "
                           f"got {self.readout!r}")


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
    image_clean: np.ndarray | None = None  # (H, W, 3) uint8 RGB before the image effects (the
    #                                        same array as ``image`` where there are none)


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


def _mover_path(rng, tf: np.ndarray, kind: str, yaw: float, speed: float, anchor: int,
                xz_anchor: np.ndarray, sub: int) -> tuple[np.ndarray, np.ndarray]:
    """A mover's ground-plane path: heading (world yaw ``yaw`` plus a slow turn and waves) and
    speed (with a slow swell) on the fine time grid ``tf``, integrated to positions, sampled every
    ``sub``-th step and anchored at frame ``anchor`` on ``xz_anchor``. Returns ((N, 2) positions,
    the fine-grid heading). The draws from ``rng`` keep their order (the legacy presets' pixels
    are pinned by checksum)."""
    deg = np.pi / 180.0
    turn = rng.uniform(-1.0, 1.0) * deg if kind == "car" else rng.uniform(-2.0, 2.0) * deg
    heading = yaw + turn * (tf - anchor)
    heading = heading + _waves(rng, tf, rng.uniform(0.0, 1.0) * deg, (20.0, 60.0))
    spd = speed * (1.0 + 0.15 * np.sin(2 * np.pi * tf / rng.uniform(20, 60)
                                      + rng.uniform(0, 2 * np.pi)))
    vel = spd[:, None] * np.stack([np.sin(heading), np.cos(heading)], axis=1)
    pos = np.concatenate([[[0.0, 0.0]], np.cumsum(0.5 * (vel[1:] + vel[:-1]) / sub, axis=0)])
    pos = pos[::sub]
    return pos - pos[anchor] + xz_anchor, heading


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


def _level_part(a: np.ndarray, size: int, k: int) -> np.ndarray:
    """The part of a (size, size // 2 + 1) rfft-layout array that mip level k keeps: the
    frequencies below its Nyquist limit, laid out as an rfft of (size >> k, size >> k)."""
    half = (size >> k) // 2
    if half >= size // 2:
        return a
    return np.concatenate([a[:half, :half + 1], a[size - half:, :half + 1]], axis=0)


@lru_cache(maxsize=8)
def _spectral_filters(size: int, slope: float = _SPECTRAL_SLOPE
                      ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per mip level k, the rfft-layout amplitude filters of the luminance and chroma fields
    (the level's part, :func:`_level_part`, float32): f^-slope times a Gaussian cut-off at the
    level's wavelength."""
    f, cutoffs = _cutoffs(size)
    power = f ** -slope
    power[0, 0] = 0.0
    out = []
    for k, (broad, chroma) in enumerate(cutoffs):
        part = _level_part(power, size, k)
        out.append(((part * broad).astype(np.float32), (part * chroma).astype(np.float32)))
    return out


@lru_cache(maxsize=4)
def _cutoffs(size: int) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """The frequency magnitude (size, size // 2 + 1) float64 (1 at DC) and, per mip level, the
    Gaussian cut-offs of the luminance and chroma filters on the level's part
    (:func:`_level_part`): the same for every slope, so the newer presets' materials (one slope
    each) compute them once per size. Built on the parts alone: a level needs a quarter of the
    coefficients of the one below (with full-size arrays a texture took about a third longer
    to build)."""
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.rfftfreq(size)[None, :]
    f = np.hypot(fx, fy)
    f[0, 0] = 1.0
    fc = 1.0 / _FINEST_WAVELENGTH_TEXELS
    out = []
    k = 0
    while size >> k >= _MIN_LEVEL_SIZE:
        fck = fc / 2 ** k
        fk = _level_part(f, size, k)
        out.append((np.exp(-(fk / fck) ** 2), np.exp(-(2.0 * fk / fck) ** 2)))
        k += 1
    return f, out


class _Texture:
    """A periodic band-limited colour texture with its mip-map.

    Level k is the same periodic function low-passed to a cut-off wavelength of
    ``_FINEST_WAVELENGTH_TEXELS * 2**k`` level-0 texels, sampled every 2**k level-0 texels; texel j
    of any level sits at coordinate j (bilinear lookups wrap around).
    """

    def __init__(self, rng, size: int, base_rgb, lum_std: float, chroma_std: float,
                 slope: float = _SPECTRAL_SLOPE, pattern: np.ndarray | None = None):
        """``pattern``: optional (size, size) float32 periodic luminance field, grey levels, added
        to every level low-passed like the luminance noise (bricks, tiles, stripes)."""
        filters = _spectral_filters(size, slope)
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
        pattern_fft = None if pattern is None else np.fft.rfft2(pattern).astype(np.complex64)
        for k, (low_broad, low_chroma) in enumerate(filters):
            sk = size >> k
            fields = []
            for j in range(3):
                s = _level_part(noise[j], size, k) * (low_broad if j == 0 else low_chroma)
                fields.append(np.fft.irfft2(s, s=(sk, sk)) * np.float32((sk / size) ** 2))
            fields = np.stack(fields, axis=-1)
            if scale is None:   # unit standard deviation of each field at level 0
                scale = 1.0 / fields.reshape(-1, 3).std(axis=0)
            rgb = base + fields @ (scale[:, None] * mix).astype(np.float32)
            if pattern_fft is not None:
                s = _level_part(pattern_fft, size, k) * _gauss_filters(size)[k]
                pat = np.fft.irfft2(s, s=(sk, sk)) * np.float32((sk / size) ** 2)
                rgb = rgb + pat[..., None].astype(np.float32) * lum_dir.astype(np.float32)
            packed = np.zeros((sk, sk, 4), dtype=np.uint8)
            packed[..., :3] = np.clip(np.rint(rgb), 0, 255)
            self.levels.append(packed.view(np.uint32).reshape(-1))
            self.sizes.append(sk)

    def _lookup(self, k: int, tu: np.ndarray, tv: np.ndarray) -> np.ndarray:
        """(3, n) float64 bilinear lookup of level k at level-0 coordinates (n,) float32 in
        [0, 2**20), channels first (R, G, B)."""
        s = self.sizes[k]
        x = tu * np.float32(0.5 ** k)
        y = tv * np.float32(0.5 ** k)
        ix = x.astype(np.int32)            # floor, as x >= 0
        iy = y.astype(np.int32)
        # float32 minus int32 is float64, exact: the blends run in float64 on whole texel values.
        wx = x - ix
        wy = y - iy
        ix1 = (ix + 1) & (s - 1)
        ix &= s - 1
        r1 = ((iy + 1) & (s - 1)) * s
        r0 = (iy & (s - 1)) * s
        # One gather for the four corners; channels first, so that every blend below runs along
        # the n samples rather than across four channels (numpy's inner loop would be 4 long).
        n = tu.shape[0]
        texels = np.take(self.levels[k], np.concatenate([r0 + ix, r0 + ix1, r1 + ix, r1 + ix1]))
        c = np.empty((3, 4, n))            # (channel, corner, sample); the pad byte left out
        c.reshape(3, 4 * n)[...] = texels.view(np.uint8).reshape(4 * n, 4)[:, :3].T
        c00, c01, c10, c11 = c[:, 0], c[:, 1], c[:, 2], c[:, 3]
        c01 -= c00
        c01 *= wx
        c01 += c00                         # top row
        c11 -= c10
        c11 *= wx
        c11 += c10                         # bottom row
        c11 -= c01
        c11 *= wy
        c11 += c01
        return c11

    def _trilinear(self, tu: np.ndarray, tv: np.ndarray, level: np.ndarray) -> np.ndarray:
        """(3, n) lookup between the mip levels floor(level) and floor(level) + 1, channels
        first."""
        n_levels = len(self.sizes)
        k0 = level.astype(np.int64)
        frac = (level - k0).astype(np.float32)
        if k0.size and k0.min() == k0.max():
            groups = [(int(k0[0]), None)]
        else:
            groups = [(k, np.flatnonzero(k0 == k)) for k in range(k0.min(initial=0),
                                                                   k0.max(initial=-1) + 1)]
        out = np.empty((3, tu.shape[0]), dtype=np.float32)
        for k, sel in groups:
            su, sv, w = (tu, tv, frac) if sel is None else (tu[sel], tv[sel], frac[sel])
            if sel is not None and sel.size == 0:
                continue
            col = self._lookup(k, su, sv)
            if k + 1 < n_levels:
                blend = np.flatnonzero(w > 0)
                if blend.size == w.size:   # all of them: no gathers
                    col += (self._lookup(k + 1, su, sv) - col) * w
                elif blend.size:
                    upper = self._lookup(k + 1, su[blend], sv[blend])
                    col[:, blend] += (upper - col[:, blend]) * w[blend]
            if sel is None:
                out = col
            else:
                out[:, sel] = col
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
        out = np.empty((3, tu.shape[0]), dtype=np.float32)   # channels first
        for m in np.unique(half_taps):
            sel = np.flatnonzero(half_taps == m)
            if m == 0:
                for c in range(0, sel.size, _CHUNK):
                    part = sel[c:c + _CHUNK]
                    out[:, part] = self._trilinear(tu[part], tv[part], level[part])
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
            taps = np.empty((su.size, 3), dtype=np.float32)
            for c in range(0, su.size, _CHUNK):   # chunks keep the temporaries in cache
                taps[c:c + _CHUNK] = self._trilinear(su[c:c + _CHUNK], sv[c:c + _CHUNK],
                                                     lev[c:c + _CHUNK]).T
            out[:, sel] = np.tensordot(w, taps.reshape(2 * m + 1, sel.size, 3), axes=1).T
        return out.T


@lru_cache(maxsize=8)
def _gauss_filters(size: int) -> list[np.ndarray]:
    """Per mip level k, the rfft-layout Gaussian cut-off float32 alone (the luminance filter
    without its f^-slope) on the level's part (:func:`_level_part`), for the patterns."""
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.rfftfreq(size)[None, :]
    f = np.hypot(fx, fy)
    fc = 1.0 / _FINEST_WAVELENGTH_TEXELS
    return [np.exp(-(_level_part(f, size, k) / (fc / 2 ** k)) ** 2).astype(np.float32)
            for k in range(len(_spectral_filters(size)))]


@dataclass(frozen=True)
class _Style:
    """How a material's texture looks (the legacy presets use the default everywhere)."""

    slope: float = _SPECTRAL_SLOPE      # amplitude spectrum ~ f^-slope
    lum_std: float = _LUM_STD           # luminance noise std, grey levels
    chroma_std: float = _CHROMA_STD     # chroma noise std, grey levels
    pattern: str = ""                   # "", "bricks", "tiles" or "stripes"
    period: int = 0                     # pattern period, texels (divides the texture size)
    pattern_amp: float = 0.0            # pattern amplitude, grey levels
    pattern_seed: int = 0               # seed of the per-brick / per-tile brightness

    @property
    def label(self) -> str:
        if self.pattern:
            return self.pattern
        return "low-texture" if self.lum_std < 6.0 else "noise"


_DEFAULT_STYLE = _Style()


def _pattern_field(style: _Style, size: int) -> np.ndarray:
    """(size, size) float32 periodic pattern of ``style`` (rows v, columns u), grey levels."""
    p = style.period
    rng = np.random.default_rng([style.pattern_seed, 7])
    v, u = np.mgrid[0:size, 0:size]
    line = max(1, p // 12)                          # mortar / grout width, texels
    if style.pattern == "bricks":
        ph = p // 2
        row = v // ph
        shifted = u + (row % 2) * (p // 2)
        mortar = ((v % ph) < line) | ((shifted % p) < line)
        brick = rng.normal(0.0, 0.35, (size // ph, size // p + 1))
        field = np.where(mortar, -1.0, brick[row, (shifted // p) % (size // p)])
    elif style.pattern == "tiles":
        grout = ((v % p) < line) | ((u % p) < line)
        tile = rng.normal(0.0, 0.3, (size // p, size // p))
        field = np.where(grout, -1.0, tile[v // p, u // p])
    elif style.pattern == "stripes":
        coord = u if rng.random() < 0.5 else v
        field = np.where((coord % p) < p // 2, 0.5, -0.5)
    else:
        raise ValueError(f"unknown pattern {style.pattern!r}")
    return (style.pattern_amp * field).astype(np.float32)


@lru_cache(maxsize=64)
def _texture(seed: int, index: int, size: int, rgb: tuple, style: _Style = _DEFAULT_STYLE,
             stream: int = -1) -> _Texture:
    """Texture of material ``index`` of the scenes of ``seed``. Cached: the street and static-box
    materials of a seed are the same for every legacy preset and size (at most 64, under 400 MB;
    a scene has up to 9, and 16 made the test suite build each one 1.5 times over).
    ``stream`` >= 0 separates the newer presets' noise from the legacy ones'."""
    rng = np.random.default_rng([seed, 4, index] if stream < 0 else [seed, 4, index, stream])
    if style == _DEFAULT_STYLE:
        return _Texture(rng, size, rgb, lum_std=_LUM_STD, chroma_std=_CHROMA_STD)
    pattern = _pattern_field(style, size) if style.pattern else None
    return _Texture(rng, size, rgb, lum_std=style.lum_std, chroma_std=style.chroma_std,
                    slope=style.slope, pattern=pattern)


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
# Recipes of the newer presets: what a seed samples (camera path, movers, effects)

_MIXED_PATH_CYCLE = ("handheld", "forward", "follow", "fast-rotation", "creep", "pan",
                     "street-walk", "slow-pan")
_MIXED_KIND_P = {"person": 0.55, "car": 0.25, "animal": 0.2}
_MIXED_BEHAVIOUR_P = {"along": 0.2, "crossing": 0.2, "oncoming": 0.12, "slow": 0.18,
                      "enter-leave": 0.2, "follow": 0.1}
_TROUSER_COLOURS = ((40, 45, 60), (60, 50, 40), (30, 30, 35), (80, 90, 110), (110, 95, 70))
_SKIN_COLOURS = ((225, 190, 160), (190, 140, 110), (140, 95, 70), (90, 60, 45))
_FUR_COLOURS = ((120, 90, 60), (60, 55, 50), (200, 190, 170), (150, 120, 80), (90, 80, 70))
_GLASS_COLOUR = (45, 55, 65)


def draw_recipe(cfg: SceneConfig) -> dict:
    """What a seed of a newer preset (creep, pan, mixed) samples, without building the scene,
    from its own stream ``[seed, 6]``: ``camera`` (a CAMERA_PATHS name), ``movers`` as (kind,
    behaviour) pairs and ``effects`` (name -> parameters). The scene's ``recipe`` is this, except
    that movers it could not place are left out."""
    rng = np.random.default_rng([cfg.seed, 6, list(PRESETS).index(cfg.preset)])
    if cfg.preset == "creep":
        behaviour = str(rng.choice(["along", "crossing", "oncoming", "slow"]))
        return {"camera": "creep", "movers": [("person", behaviour)], "effects": {}}
    if cfg.preset == "pan":
        kind = "car" if rng.random() < 0.3 else "person"
        behaviour = str(rng.choice(["along", "crossing", "oncoming"]))
        return {"camera": "pan", "movers": [(kind, behaviour)], "effects": {}}
    # The camera path cycles with the seed, so any 8 consecutive seeds hold every path.
    camera = _MIXED_PATH_CYCLE[cfg.seed % len(_MIXED_PATH_CYCLE)]
    camera = camera if cfg.camera_path is None else cfg.camera_path
    count = int(rng.choice([1, 2, 3], p=[0.45, 0.35, 0.2]))
    movers: list[tuple[str, str]] = []
    if camera == "follow":
        movers.append(("person", "follow"))
    elif camera == "forward" and rng.random() < 0.5:
        movers.append(("car", "follow"))
    if count - len(movers) >= 2 and rng.random() < 0.4:
        kind = "person" if rng.random() < 0.75 else "animal"
        movers += [(kind, "cross-pair"), ("person", "cross-pair")]
    kinds, kp = list(_MIXED_KIND_P), list(_MIXED_KIND_P.values())
    behaviours = list(_MIXED_BEHAVIOUR_P)
    bp = np.array(list(_MIXED_BEHAVIOUR_P.values()))
    if camera in ("pan", "slow-pan", "creep"):      # nothing to keep pace with
        bp[behaviours.index("follow")] = 0.0
    bp = bp / bp.sum()
    while len(movers) < count:
        kind = str(rng.choice(kinds, p=kp))
        if kind == "car" and any(k == "car" for k, _ in movers):
            kind = "person"
        movers.append((kind, str(rng.choice(behaviours, p=bp))))
    effects: dict[str, dict] = {}
    if rng.random() < 0.5:
        effects["motion_blur"] = {"shutter": round(float(rng.uniform(0.3, 0.9)), 3)}
    if rng.random() < 0.6:
        effects["noise"] = {"sigma": round(float(rng.uniform(1.0, 4.0)), 3),
                            "shot": round(float(rng.uniform(0.0, 0.05)), 4)}
    if rng.random() < 0.4:
        effects["exposure"] = {"amplitude": round(float(rng.uniform(0.1, 0.3)), 3),
                               "period": round(float(rng.uniform(20.0, 60.0)), 2),
                               "phase": round(float(rng.uniform(0.0, 2.0 * np.pi)), 4)}
    if rng.random() < 0.5:
        effects["jpeg"] = {"quality": int(rng.integers(35, 91))}
    return {"camera": camera, "movers": movers, "effects": effects}


def _draw_style(rng, role: str, size: int, index: int) -> _Style:
    """A texture style with natural-image statistics for a material of the ``mixed`` preset:
    1/f-like spectra (amplitude slope 0.85-1.15), contrast 12-40 grey levels, or a low-texture
    surface (1.5-5), or a repetitive pattern (bricks, tiles, stripes)."""
    p_low = {"sky": 0.6, "mover": 0.3, "static": 0.25}.get(role, 0.2)
    p_pattern = {"sky": 0.0, "mover": 0.15, "static": 0.2}.get(role, 0.3)
    u = rng.random()
    if u < p_low:
        return _Style(slope=float(rng.uniform(1.0, 1.3)), lum_std=float(rng.uniform(1.5, 5.0)),
                      chroma_std=float(rng.uniform(0.5, 2.0)))
    if u < p_low + p_pattern:
        kinds = {"floor": ["tiles", "bricks"], "mover": ["stripes"],
                 "static": ["stripes", "tiles"]}.get(role, ["bricks", "tiles", "stripes"])
        periods = [q for q in (16, 32, 64) if q <= size // 4]
        return _Style(slope=float(rng.uniform(0.85, 1.15)), lum_std=float(rng.uniform(5.0, 15.0)),
                      chroma_std=float(rng.uniform(2.0, 6.0)), pattern=str(rng.choice(kinds)),
                      period=int(rng.choice(periods)), pattern_amp=float(rng.uniform(12.0, 30.0)),
                      pattern_seed=int(rng.integers(0, 2 ** 31)))
    return _Style(slope=float(rng.uniform(0.85, 1.15)), lum_std=float(rng.uniform(12.0, 40.0)),
                  chroma_std=float(rng.uniform(2.0, 6.0)))


def _shake(rng, t, rate, periods=(3.0, 10.0), k: int = 3):
    """Hand-held jitter: k sinusoids of periods in ``periods`` (frames), each of peak rate
    ``rate / 2`` per frame."""
    return sum(_waves(rng, t, rate / 2.0, periods) for _ in range(k))


def _rotations(yaw, pitch, roll) -> np.ndarray:
    return np.stack([_rot_y(a) @ _rot_x(p) @ _rot_z(r) for a, p, r in zip(yaw, pitch, roll)])


# ----------------------------------------------------------------------------------------------
# The scene


@dataclass
class _MoverProposal:
    kind: str
    half: np.ndarray      # (3,) half extents, metres
    xz: np.ndarray        # (N, 2) ground position per frame, metres
    heading: np.ndarray   # (N,) radians, direction (sin, cos) in (x, z)
    behaviour: str = ""   # newer presets: a name in MOVER_BEHAVIOURS
    anchor: int = 0       # frame at which the mover is placed in front of the camera
    bearing: float = 0.0  # radians from the optical axis at the anchor frame
    dist: float = 0.0     # metres from the camera at the anchor frame
    rel: float = 0.0      # radians, heading relative to the camera yaw at the anchor frame
    shape: dict = field(default_factory=dict)   # articulated-shape parameters (newer presets)


class SyntheticScene:
    """A rendered-on-demand synthetic sequence with exact ground truth (see the module docstring).

    ``len(scene)`` frames; iterate for lazily rendered :class:`RenderedFrame` objects.
    """

    def __init__(self, config: SceneConfig | None = None):
        self.config = config if config is not None else SceneConfig()
        cfg = self.config
        n = cfg.n_frames
        fast = cfg.preset == "fast-rotation"
        self._legacy = cfg.preset in LEGACY_PRESETS
        self._stream = -1 if self._legacy else 100 + list(PRESETS).index(cfg.preset)
        self.recipe: dict | None = None if self._legacy else draw_recipe(cfg)
        self._style_rng = np.random.default_rng([cfg.seed, 8])

        rng = np.random.default_rng([cfg.seed, 1])
        hfov_range = (40.0, 90.0) if cfg.preset == "mixed" else (55.0, 75.0)
        hfov = np.radians(rng.uniform(*hfov_range) if cfg.hfov_deg is None else cfg.hfov_deg)
        f = 0.5 * fov_span(cfg.width, cfg.height) / np.tan(hfov / 2.0)
        pp = rng.uniform(-0.02, 0.02, 2)
        self.intrinsics = Intrinsics(float(f), float(f),
                                     float((cfg.width - 1) / 2.0 + pp[0] * cfg.width),
                                     float((cfg.height - 1) / 2.0 + pp[1] * cfg.height))
        # Movers are placed across the horizontal field of view, narrower than the drawn one on a
        # portrait frame.
        self._hfov = float(hfov) if cfg.width >= cfg.height else float(2 * np.arctan(0.5 * cfg.width / f))
        if self._legacy:
            self._R_wc, self._centres, self._yaw = self._camera_path(rng, n, fast)
        else:
            self._R_wc, self._centres, self._yaw = self._camera_path_v2(rng, n,
                                                                        self.recipe["camera"])
        self._poses = np.stack([make_pose(R, c) for R, c in zip(self._R_wc, self._centres)])

        rng = np.random.default_rng([cfg.seed, 2])
        if self._legacy:
            self._boxes: list[_Box] = [self._street(rng)]
            self._boxes += self._static_boxes(rng)
        else:
            room = self.recipe["camera"] == "creep"   # near end wall, boxes kept 3.5 m away
            self._boxes = [self._street(rng, width_range=(8.0, 12.0) if room else (12.0, 16.0),
                                        ahead=(10.0, 18.0) if room else (25.0, 35.0))]
            self._boxes += self._static_boxes(rng, clearance=3.5 if room else _STATIC_CLEARANCE)
        self.n_static = len(self._boxes) - 1

        gw = _COVERAGE_GRID_WIDTH
        gh = max(int(round(gw * cfg.height / cfg.width)), 8)
        self._coverage_grid = _Grid.make(gw, gh, self.intrinsics.scaled(gw / cfg.width,
                                                                        gh / cfg.height))
        rng = np.random.default_rng([cfg.seed, 3, list(PRESETS).index(cfg.preset)])
        self._boxes += self._movers(rng) if self._legacy else self._movers_v2(rng)
        first_box = {}
        for b in self._boxes:
            if b.mover and b.mover not in first_box:
                first_box[b.mover] = b.kind
        self.n_movers = len(first_box)
        self.mover_kinds = tuple(first_box[k] for k in sorted(first_box))
        self._grid = _Grid.make(cfg.width, cfg.height, self.intrinsics)
        if not self._legacy:
            self._gain = self._exposure_gains()

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

    def geometry(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame i's exact depth (H, W) float32 metres and object ids (H, W) uint8 (0 static, k
        mover k), ray-cast without texturing (fast; equal to :meth:`render`'s)."""
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} out of range 0..{len(self) - 1}")
        t, box, _ = self._trace_frame(i)
        mover_of_box = np.array([b.mover for b in self._boxes], dtype=np.uint8)
        return t.astype(np.float32), mover_of_box[box]

    def render(self, i: int) -> RenderedFrame:
        """Frame i (0 <= i < len(scene)) with its ground truth."""
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} out of range 0..{len(self) - 1}")
        bands = self._row_bands(i)
        t, box, face = self._trace_frame(i, bands)
        face_id = (box.astype(np.int16) * 6 + face).astype(np.int16)
        image = np.concatenate([self._shade(i, t[y0:y1], face_id[y0:y1], R_wc, c, grid)
                                for y0, y1, R_wc, c, grid in bands])
        mover_of_box = np.array([b.mover for b in self._boxes], dtype=np.uint8)
        object_id = mover_of_box[box]
        clean = image
        if self.recipe is not None and self.recipe["effects"] and self.config.effects:
            image = self._apply_effects(i, image, t, box)
        return RenderedFrame(index=i, image=image, depth=t.astype(np.float32),
                             mask=object_id > 0, object_id=object_id, face_id=face_id,
                             T_world_cam=self._poses[i].copy(), intrinsics=self.intrinsics,
                             image_clean=clean)

    def _row_bands(self, i: int) -> list[tuple[int, int, np.ndarray, np.ndarray, _Grid]]:
        """(first row, end row, R_wc, centre, grid of those rows) of each band of frame i's rows
        read at one instant: the whole frame at frame i's pose under a global shutter; under a
        rolling shutter (``SceneConfig.readout``) bands of 4 rows, each at the camera's pose when
        its middle row was read, ``readout * (v - (H - 1) / 2) / H`` frame intervals after the
        frame's middle row (rotation and centre interpolated between the frames on either side,
        extrapolated at the ends). The frame's pose is its middle row's, as for the VO
        (mona_vo.rolling_shutter). Movers stay at the frame's state: they are masked, and the
        shutter matters for the static scene the camera's trajectory is read from."""
        grid = self._grid
        readout = float(self.config.readout)
        if readout == 0.0:
            return [(0, grid.height, self._R_wc[i], self._centres[i], grid)]
        from scipy.spatial.transform import Rotation

        n, H = len(self), grid.height
        bands = []
        for y0 in range(0, H, _SHUTTER_BAND_ROWS):
            y1 = min(y0 + _SHUTTER_BAND_ROWS, H)
            s = readout * ((y0 + y1 - 1) / 2.0 - (H - 1) / 2.0) / H
            j = min(i + 1, n - 1) if s >= 0 else max(i - 1, 0)
            if j == i:                      # the first or last frame: the step on its other side
                j = i - 1 if s >= 0 else i + 1
            step = (j - i) * s              # the fraction of the step from i to j, negative beyond i
            R_i, R_j = self._R_wc[i], self._R_wc[j]
            turn = Rotation.from_matrix(R_i.T @ R_j).as_rotvec() * step
            R = R_i @ Rotation.from_rotvec(turn).as_matrix()
            c = self._centres[i] + step * (self._centres[j] - self._centres[i])
            band = _Grid(grid.width, y1 - y0,
                         Intrinsics(grid.intr.fx, grid.intr.fy, grid.intr.cx, grid.intr.cy - y0),
                         grid.a, grid.b[y0:y1])
            bands.append((y0, y1, R, c, band))
        return bands

    def _trace_frame(self, i: int, bands: list | None = None):
        """:func:`_trace` of frame i, band by band of rows read at one instant (``bands``, by
        default :meth:`_row_bands`)."""
        bands = self._row_bands(i) if bands is None else bands
        parts = [_trace(self._boxes, i, R_wc, c, grid) for _, _, R_wc, c, grid in bands]
        if len(parts) == 1:
            return parts[0]
        return tuple(np.concatenate(p) for p in zip(*parts))

    # -- shading ------------------------------------------------------------------------------

    @cached_property
    def _textures(self) -> list[_Texture]:
        if self._legacy:
            return [_texture(self.config.seed, m, size, rgb)
                    for m, (size, _, rgb, _) in enumerate(self._materials)]
        return [_texture(self.config.seed, m, size, rgb, style, self._stream)
                for m, (size, _, rgb, style) in enumerate(self._materials)]

    def _shade(self, i: int, t: np.ndarray, face_id: np.ndarray, R_wc: np.ndarray, c: np.ndarray,
               grid: _Grid) -> np.ndarray:
        intr = grid.intr
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

    def _material(self, size: int, density: float, rgb, role: str = "wall") -> int:
        """A new material: texture size, texels per metre = density * fx, base colour RGB; the
        ``mixed`` preset draws its texture style for the ``role`` (wall, floor, sky, static,
        mover) from its own stream."""
        if not self._legacy:   # the texture's period in metres stays about the same at any fx
            scale = 2.0 ** np.ceil(np.log2(max(self.intrinsics.fx, 1.0) / 800.0))
            size = int(np.clip(size * scale, 64, size))
        style = (_draw_style(self._style_rng, role, size, len(self._materials))
                 if self.config.preset == "mixed" else _DEFAULT_STYLE)
        self._materials.append((size, density * self.intrinsics.fx, tuple(int(v) for v in rgb),
                                style))
        return len(self._materials) - 1

    def _street(self, rng, width_range=(12.0, 16.0), ahead=(25.0, 35.0)) -> _Box:
        n = self.config.n_frames
        zc = self._centres[:, 2]
        width = rng.uniform(*width_range)
        height = rng.uniform(7.0, 9.0)
        z0 = zc.min() - rng.uniform(4.0, 7.0)
        z1 = zc.max() + rng.uniform(*ahead)
        self._street_extent = (width, height, z0, z1)
        self._materials: list[tuple] = []
        walls = rng.choice(len(_WORLD_COLOURS), 4, replace=False)
        jitter = rng.uniform(-8, 8, (4, 3))
        colours = [np.add(_WORLD_COLOURS[k], j) for k, j in zip(walls, jitter)]
        left = self._material(1024, _STREET_DENSITY, colours[0])
        right = self._material(1024, _STREET_DENSITY, colours[1])
        floor = self._material(1024, _STREET_DENSITY, colours[2] * 0.85, role="floor")
        ends = self._material(1024, _STREET_DENSITY, colours[3])
        sky = self._material(1024, _SKY_DENSITY, _SKY_COLOUR, role="sky")
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

    def _static_boxes(self, rng, clearance: float = _STATIC_CLEARANCE) -> list[_Box]:
        n = self.config.n_frames
        width, height, z0, z1 = self._street_extent
        mats = [self._material(512, _STATIC_DENSITY,
                               np.add(_STATIC_COLOURS[k], rng.uniform(-8, 8, 3)), role="static")
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
            if dist.min() < clearance:
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
        pos, heading = _mover_path(rng, tf, kind, cam_yaw + rel, speed, anchor, xz_anchor, sub)
        return _MoverProposal(kind=kind, half=size / 2.0, xz=pos, heading=heading[::sub].copy())

    def _check(self, prop: _MoverProposal, accepted, covs, rule=None) -> np.ndarray | None:
        """The proposal's per-frame coverage on the coarse grid when it is admissible, else None.
        ``rule(cov, total)`` replaces the legacy presets' coverage rule (newer presets)."""
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
                sel = ~np.isnan(cov)
                if rule is None:
                    if not self._coverage_ok(preset, done, covs, sel):
                        return None
                elif not rule(done, done + sum(o[sel] for o in covs)):
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
        mat = self._material(1024, _MOVER_DENSITY, rgb, role="mover")
        R = np.stack([_rot_y(h) for h in prop.heading])
        centre = np.column_stack([prop.xz[:, 0], np.full(n, -prop.half[1]), prop.xz[:, 1]])
        return _Box(half=prop.half, R=R, centre=centre, materials=(mat,) * 6,
                    offsets=rng.uniform(0.0, 1024.0, (6, 2)),
                    brightness=self._box_brightness(rng), mover=k, kind=prop.kind)


    # -- newer presets: camera paths ----------------------------------------------------------

    def _camera_path_v2(self, rng, n: int, kind: str):
        """Rotations (N, 3, 3), centres (N, 3) and yaw (N,) of a camera path in CAMERA_PATHS."""
        if kind == "street-walk":
            return self._camera_path(rng, n, False)
        if kind == "fast-rotation":
            return self._camera_path(rng, n, True)
        t = np.arange(n, dtype=np.float64)
        deg = np.pi / 180.0
        x0 = rng.uniform(-1.0, 1.0)
        y0 = -rng.uniform(1.2, 1.6) if kind == "forward" else -rng.uniform(1.4, 1.8)
        yaw0 = rng.uniform(-10.0, 10.0) * deg
        pitch0 = rng.uniform(-4.0, 2.0) * deg
        roll0 = rng.uniform(-1.5, 1.5) * deg
        zeros = np.zeros(n)
        if kind in ("pan", "slow-pan"):
            rate = (rng.uniform(0.5, 2.0) if kind == "pan" else rng.uniform(0.2, 0.6)) * deg
            omega = 2.0 * np.pi / rng.uniform(30.0, 90.0)
            phase = rng.uniform(0.0, 2.0 * np.pi)
            sweep = rate * (t + 0.25 / omega * (np.cos(phase) - np.cos(omega * t + phase)))
            yaw = yaw0 + rng.choice([-1.0, 1.0]) * sweep
            pitch = pitch0 + _waves(rng, t, rng.uniform(0.05, 0.2) * deg, (30.0, 90.0))
            roll = roll0 + _waves(rng, t, rng.uniform(0.0, 0.03) * deg, (30.0, 90.0))
            if kind == "pan":     # tripod: the centre never moves
                centres = np.tile([x0, y0, 0.0], (n, 1))
            else:
                step = rng.uniform(0.003, 0.015)
                direction = yaw0 + rng.choice([-1.0, 1.0]) * rng.uniform(60.0, 120.0) * deg
                centres = np.column_stack([x0 + step * t * np.sin(direction),
                                           y0 + _waves(rng, t, 0.0005, (20.0, 60.0)),
                                           step * t * np.cos(direction)])
            return _rotations(yaw, pitch, roll), centres, yaw
        if kind == "creep":
            speed = rng.uniform(0.008, 0.012)
            psi = yaw0 + rng.uniform(-90.0, 90.0) * deg          # direction of the creep
            rise = rng.uniform(-0.2, 0.2)
            direction = np.array([np.sin(psi), rise, np.cos(psi)]) / np.sqrt(1.0 + rise * rise)
            centres = (np.array([x0, y0, 0.0]) + speed * t[:, None] * direction
                       + np.column_stack([_shake(rng, t, 0.0006, (6.0, 20.0)) for _ in range(3)]))
            yaw = (yaw0 + _waves(rng, t, rng.uniform(0.02, 0.1) * deg, (40.0, 120.0))
                   + _shake(rng, t, rng.uniform(0.03, 0.1) * deg))
            pitch = pitch0 + _shake(rng, t, rng.uniform(0.03, 0.08) * deg)
            roll = roll0 + _shake(rng, t, rng.uniform(0.02, 0.06) * deg)
            return _rotations(yaw, pitch, roll), centres, yaw
        # Walking or driving along the street: handheld, follow, forward.
        if kind == "handheld":
            speed, turn, shake = rng.uniform(0.01, 0.04), rng.uniform(0.1, 0.3), rng.uniform(0.15, 0.5)
            trans_shake, bob = rng.uniform(0.002, 0.005), 0.0
        elif kind == "follow":
            speed, turn, shake = rng.uniform(0.025, 0.05), rng.uniform(0.1, 0.3), rng.uniform(0.08, 0.25)
            trans_shake, bob = 0.001, rng.uniform(0.003, 0.006)
        elif kind == "forward":
            speed, turn, shake = rng.uniform(0.2, 0.45), rng.uniform(0.1, 0.4), rng.uniform(0.02, 0.06)
            trans_shake, bob = 0.0005, 0.0
        else:
            raise ValueError(f"unknown camera path {kind!r}")
        heading = yaw0 + _waves(rng, t, turn * deg, (40.0, 120.0))
        step = speed * (1.0 + 0.15 * np.sin(2 * np.pi * t / rng.uniform(20, 60) + rng.uniform(0, 6.3)))
        vx = step * np.sin(heading)
        vz = step * np.cos(heading)
        x = x0 + np.concatenate([[0.0], np.cumsum(vx[1:])]) + _shake(rng, t, trans_shake)
        z = np.concatenate([[0.0], np.cumsum(vz[1:])]) + _shake(rng, t, trans_shake)
        y = y0 + _waves(rng, t, bob, (12.0, 20.0)) + _shake(rng, t, trans_shake)
        yaw = heading + _shake(rng, t, shake * deg)
        pitch = pitch0 + _shake(rng, t, 0.7 * shake * deg)
        roll = roll0 + _shake(rng, t, 0.5 * shake * deg)
        del zeros
        return _rotations(yaw, pitch, roll), np.column_stack([x, y, z]), yaw

    # -- newer presets: movers ----------------------------------------------------------------

    def _movers_v2(self, rng) -> list[_Box]:
        """Movers of the recipe, each placed by its behaviour's rule; a mover that cannot be
        placed after the first is left out (``recipe['movers']`` then lists what was placed)."""
        wanted = list(self.recipe["movers"])
        accepted: list[_MoverProposal] = []
        covs: list[np.ndarray] = []
        placed: list[tuple[str, str]] = []
        for m, (kind, behaviour) in enumerate(wanted):
            ref = None
            if behaviour == "cross-pair":
                refs = [a for a, b in zip(accepted, placed) if b[1] == "cross-pair"]
                ref = refs[0] if refs else None
            prop = self._place(rng, kind, behaviour, ref, accepted, covs)
            if prop is None and m == 0:
                kind, behaviour = "person", "slow"     # the easiest mover to place
                prop = self._place(rng, kind, behaviour, None, accepted, covs)
            if prop is None:
                if m == 0:
                    cfg = self.config
                    raise MonaVoError(
                        f"synthetic scene: could not place a mover of preset {cfg.preset!r} for "
                        f"seed {cfg.seed} and {cfg.n_frames} frames in {_MAX_TRIES} tries; "
                        f"use another seed or fewer frames")
                log.debug("mover %d (%s, %s) could not be placed; left out", m + 1, kind,
                          behaviour)
                continue
            accepted.append(prop[0])
            covs.append(prop[1])
            placed.append((kind, behaviour))
        # A crossing pair whose second mover was left out is one crossing mover.
        if sum(b == "cross-pair" for _, b in placed) == 1:
            placed = [(k, "crossing" if b == "cross-pair" else b) for k, b in placed]
        self.recipe["movers"] = placed
        colours = rng.permutation(len(_PERSON_COLOURS))
        boxes = []
        for k, prop in enumerate(accepted):
            boxes += self._mover_parts(rng, prop, k + 1, int(colours[k % len(colours)]))
        return boxes

    def _place(self, rng, kind, behaviour, ref, accepted, covs):
        """(proposal, coarse coverage) of the first admissible proposal, or None."""
        rule = functools.partial(self._rule_v2, behaviour)
        for attempt in range(_MAX_TRIES):
            prop = self._propose_v2(rng, kind, behaviour, ref)
            cov = self._check(prop, accepted, covs, rule=rule)
            if cov is None:
                continue
            # By identity: proposals are dataclasses of arrays, whose == cannot be a bool.
            if ref is not None and not self._crosses(
                    prop, ref, cov, covs[next(i for i, a in enumerate(accepted) if a is ref)]):
                continue
            log.debug("mover %s/%s accepted after %d proposals", kind, behaviour, attempt + 1)
            return prop, cov
        return None

    def _rule_v2(self, behaviour: str, cov: np.ndarray, total: np.ndarray) -> bool:
        """Coverage rule of one mover of a newer preset on the coarse grid (frames in order)."""
        if np.any(total > _MAX_COVERAGE) or cov.max() > 0.4:
            return False
        visible = cov > _VISIBLE_COVERAGE
        if behaviour == "enter-leave":
            return bool(0.2 <= visible.mean() <= 0.85 and not (visible[0] and visible[-1]))
        need = {"creep": 0.7, "pan": 0.5}.get(self.config.preset, 0.6)
        return bool(visible.mean() >= (0.5 if behaviour == "cross-pair" else need))

    def _crosses(self, a: _MoverProposal, b: _MoverProposal, cov_a, cov_b) -> bool:
        """Whether the image x of mover a's centre passes mover b's while both are visible."""
        xs = []
        for prop in (a, b):
            X = np.column_stack([prop.xz[:, 0], np.full(len(prop.xz), -prop.half[1]),
                                 prop.xz[:, 1]])
            pc = np.einsum("nji,nj->ni", self._R_wc, X - self._centres)
            xs.append((pc[:, 0] / np.maximum(pc[:, 2], 1e-6), pc[:, 2] > 0.3))
        ok = xs[0][1] & xs[1][1] & (cov_a > _VISIBLE_COVERAGE) & (cov_b > _VISIBLE_COVERAGE)
        if ok.sum() < 2:
            return False
        d = (xs[0][0] - xs[1][0])[ok]
        return bool(d.min() < 0.0 < d.max())

    @staticmethod
    def _shape(rng, kind: str) -> tuple[np.ndarray, dict]:
        """Bounding size (3,) metres (x across, y height, z along the heading) and the shape
        parameters of an articulated person, an animal or a car."""
        deg = np.pi / 180.0
        if kind == "person":
            h = rng.uniform(1.55, 1.9)
            amp = rng.uniform(18.0, 28.0) * deg
            half_z = max(0.47 * h * np.sin(amp) + 0.045 * h, 0.36 * h * np.sin(0.7 * amp) + 0.03 * h,
                         0.07 * h)
            return (np.array([0.34 * h, h, 2.0 * half_z]),
                    {"height": h, "amp": amp, "stride": 1.3 * h / 1.75, "bulk": rng.uniform(0.9, 1.1)})
        if kind == "animal":
            length = rng.uniform(0.6, 1.0)
            height = rng.uniform(0.45, 0.75)
            width = rng.uniform(0.22, 0.35)
            amp = rng.uniform(15.0, 30.0) * deg
            return (np.array([width, height + 0.12, 1.5 * length]),
                    {"length": length, "height": height, "width": width, "amp": amp,
                     "stride": 0.8 * length})
        size = rng.uniform([1.7, 1.4, 3.9], [1.95, 1.6, 4.7])
        return size, {"cabin_offset": rng.uniform(-0.12, 0.0), "cabin_length": rng.uniform(0.45, 0.6)}

    def _propose_v2(self, rng, kind: str, behaviour: str, ref=None) -> _MoverProposal:
        """A mover trajectory of the given kind and behaviour (MOVER_BEHAVIOURS), anchored in
        front of the camera; the second of a crossing pair starts from ``ref``'s anchor."""
        n = self.config.n_frames
        deg = np.pi / 180.0
        size, shape = self._shape(rng, kind)
        dist = {"person": (2.0, 9.0), "animal": (2.0, 6.0), "car": (5.0, 14.0)}[kind]
        if self.config.preset == "creep":
            dist = (2.5, 8.0)
        cam_speed = np.linalg.norm(np.diff(self._centres[:, [0, 2]], axis=0), axis=1).mean()
        spread = 0.15 if behaviour == "follow" else 0.4
        bearing = rng.uniform(-spread, spread) * self._hfov
        if behaviour == "enter-leave":
            anchor = int(round((rng.uniform(0.0, 0.25) if rng.random() < 0.5
                                else rng.uniform(0.75, 1.0)) * (n - 1)))
        else:
            anchor = int(round(rng.uniform(0.3, 0.7) * (n - 1)))
        d = rng.uniform(*dist)
        if ref is not None:
            anchor, bearing = ref.anchor, ref.bearing
            d = max(ref.dist + rng.choice([-1.0, 1.0]) * rng.uniform(1.5, 4.0), dist[0])
        cam_yaw = self._yaw[anchor]
        xz_anchor = self._centres[anchor, [0, 2]] + d * np.array(
            [np.sin(cam_yaw + bearing), np.cos(cam_yaw + bearing)])
        sub = 8
        tf = np.arange((n - 1) * sub + 1, dtype=np.float64) / sub
        common = dict(kind=kind, half=size / 2.0, behaviour=behaviour, anchor=anchor,
                      bearing=float(bearing), dist=float(d), shape=shape)
        if behaviour == "follow":
            x = xz_anchor[0] + _waves(rng, tf, rng.uniform(0.0, 0.02), (30.0, 90.0))
            z = (np.interp(tf, np.arange(n), self._centres[:, 2]) - self._centres[anchor, 2]
                 + xz_anchor[1] + _waves(rng, tf, rng.uniform(0.0, 0.03), (30.0, 90.0)))
            pos = np.stack([x, z], axis=1)
            vel = np.gradient(pos, tf, axis=0)
            heading = np.arctan2(vel[:, 0], vel[:, 1])
            pos = pos - pos[anchor * sub] + xz_anchor
            return _MoverProposal(xz=pos[::sub].copy(), heading=heading[::sub].copy(), rel=0.0,
                                  **common)
        speeds = {  # m/frame by behaviour: person, animal, car
            "along": ((0.025, 0.06), (0.03, 0.08), None),
            "crossing": ((0.025, 0.05), (0.03, 0.07), (0.04, 0.12)),
            "cross-pair": ((0.025, 0.05), (0.03, 0.07), (0.04, 0.12)),
            "enter-leave": ((0.04, 0.07), (0.05, 0.1), (0.08, 0.2)),
            "oncoming": ((0.025, 0.05), (0.03, 0.07), (0.05, 0.15)),
            "slow": ((0.003, 0.012), (0.004, 0.015), (0.01, 0.03)),
        }[behaviour][("person", "animal", "car").index(kind)]
        if speeds is None:    # a car along the street at about the camera's pace
            speed = max(cam_speed * rng.uniform(0.7, 1.3), 0.04)
        else:
            speed = rng.uniform(*speeds)
        if behaviour == "along":
            rel = rng.uniform(-25.0, 25.0) * deg
        elif behaviour in ("crossing", "enter-leave"):
            rel = rng.choice([-1.0, 1.0]) * rng.uniform(60.0, 120.0) * deg
        elif behaviour == "cross-pair":
            side = 1.0 if ref is None else -np.sign(ref.rel)
            rel = side * rng.uniform(75.0, 105.0) * deg
        elif behaviour == "oncoming":
            rel = np.pi + rng.uniform(-20.0, 20.0) * deg
        else:
            rel = rng.uniform(-np.pi, np.pi)
        pos, heading = _mover_path(rng, tf, kind, cam_yaw + rel, speed, anchor, xz_anchor, sub)
        return _MoverProposal(xz=pos, heading=heading[::sub].copy(), rel=float(rel), **common)

    def _mover_parts(self, rng, prop: _MoverProposal, k: int, colour: int) -> list[_Box]:
        """The boxes of mover k: an articulated person (legs and arms swinging with the distance
        walked), an animal (four swinging legs) or a car (body and cabin), all labelled k."""
        n = self.config.n_frames
        sh = prop.shape
        Rh = np.stack([_rot_y(h) for h in prop.heading])            # (N, 3, 3) mover frame
        ground = np.column_stack([prop.xz[:, 0], np.zeros(n), prop.xz[:, 1]])
        walked = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(prop.xz, axis=0),
                                                                 axis=1))])
        parts: list[tuple] = []   # (half (3,), pivot (3,), offset (3,), swing (N,), material)

        def mat(palette, jitter=10.0, size=256):
            rgb = np.add(palette[int(rng.integers(len(palette)))], rng.uniform(-jitter, jitter, 3))
            return self._material(size, _MOVER_DENSITY, rgb, role="mover")

        if prop.kind == "person":
            h, amp = sh["height"], sh["amp"]
            speed = walked[-1] / max(n - 1, 1)
            amp = amp * float(np.clip(speed / 0.035, 0.25, 1.0))
            phase = 2.0 * np.pi * walked / sh["stride"] + rng.uniform(0, 2 * np.pi)
            if prop.behaviour == "slow":   # shifting, gesturing: limbs move with time as well
                phase = phase + 2.0 * np.pi * np.arange(n) / rng.uniform(20.0, 40.0)
            swing = amp * np.sin(phase)
            top = mat(_PERSON_COLOURS)
            legs = mat(_TROUSER_COLOURS)
            skin = mat(_SKIN_COLOURS)
            b = sh["bulk"]
            leg = 0.47 * h
            for side in (-1.0, 1.0):
                parts.append((np.array([0.04 * h * b, leg / 2.0, 0.045 * h]),
                              np.array([side * 0.055 * h * b, -leg, 0.0]),
                              np.array([0.0, leg / 2.0, 0.0]), side * swing, legs))
                parts.append((np.array([0.025 * h, 0.18 * h, 0.028 * h]),
                              np.array([side * 0.14 * h * b, -0.81 * h, 0.0]),
                              np.array([0.0, 0.18 * h, 0.0]), -0.7 * side * swing, top))
            parts.append((np.array([0.11 * h * b, 0.18 * h, 0.06 * h * b]), np.array([0.0, -0.65 * h, 0.0]),
                          np.zeros(3), np.zeros(n), top))
            parts.append((np.array([0.055 * h, 0.085 * h, 0.06 * h]), np.array([0.0, -0.915 * h, 0.0]),
                          np.zeros(3), np.zeros(n), skin))
        elif prop.kind == "animal":
            length, height, width, amp = sh["length"], sh["height"], sh["width"], sh["amp"]
            phase = 2.0 * np.pi * walked / sh["stride"] + rng.uniform(0, 2 * np.pi)
            if prop.behaviour == "slow":
                phase = phase + 2.0 * np.pi * np.arange(n) / rng.uniform(15.0, 30.0)
            swing = amp * np.sin(phase)
            fur = mat(_FUR_COLOURS, jitter=15.0)
            leg = 0.55 * height
            lw = 0.06 + 0.1 * width
            for sx in (-1.0, 1.0):
                for sz in (-1.0, 1.0):
                    parts.append((np.array([lw / 2.0, leg / 2.0, lw / 2.0]),
                                  np.array([sx * (width / 2.0 - lw / 2.0), -leg,
                                            sz * (length / 2.0 - lw / 2.0 - 0.03)]),
                                  np.array([0.0, leg / 2.0, 0.0]), sx * sz * swing, fur))
            parts.append((np.array([width / 2.0, 0.225 * height, length / 2.0]),
                          np.array([0.0, -0.775 * height, 0.0]), np.zeros(3), np.zeros(n), fur))
            head = 0.13 * length + 0.04
            parts.append((np.array([0.4 * width, head * 0.8, head]),
                          np.array([0.0, -(height + 0.12 - head * 0.8), length / 2.0 + 0.25 * length - head]),
                          np.zeros(3), np.zeros(n), fur))
        else:
            w, hgt, length = prop.half * 2.0
            body_h = 0.55 * hgt
            paint = self._material(1024, _MOVER_DENSITY,
                                   np.add(_CAR_COLOURS[colour % len(_CAR_COLOURS)],
                                          rng.uniform(-10, 10, 3)), role="mover")
            glass = self._material(256, _MOVER_DENSITY, _GLASS_COLOUR, role="mover")
            parts.append((np.array([w / 2.0, body_h / 2.0, length / 2.0]),
                          np.array([0.0, -body_h / 2.0, 0.0]), np.zeros(3), np.zeros(n), paint))
            cab_l = sh["cabin_length"] * length
            parts.append((np.array([0.44 * w, (hgt - body_h) / 2.0, cab_l / 2.0]),
                          np.array([0.0, -(body_h + (hgt - body_h) / 2.0),
                                    sh["cabin_offset"] * length]),
                          np.zeros(3), np.zeros(n), glass))
        boxes = []
        for half, pivot, offset, swing, material in parts:
            Rs = np.stack([_rot_x(a) for a in swing])                     # (N, 3, 3)
            R = Rh @ Rs
            local = pivot[None, :] + np.einsum("nij,j->ni", Rs, offset)
            centre = ground + np.einsum("nij,nj->ni", Rh, local)
            boxes.append(_Box(half=half, R=R, centre=centre, materials=(material,) * 6,
                              offsets=rng.uniform(0.0, 256.0, (6, 2)),
                              brightness=self._box_brightness(rng), mover=k, kind=prop.kind))
        return boxes

    # -- newer presets: image effects ---------------------------------------------------------

    def _exposure_gains(self) -> np.ndarray:
        """(N,) float64 exposure gain per frame (1 without the exposure effect)."""
        n = self.config.n_frames
        e = self.recipe["effects"].get("exposure")
        if e is None:
            return np.ones(n)
        t = np.arange(n, dtype=np.float64)
        return np.exp(e["amplitude"] * np.sin(2.0 * np.pi * t / e["period"] + e["phase"]))

    def _flow(self, i: int, t: np.ndarray, box: np.ndarray) -> np.ndarray:
        """(H, W, 2) float32 exact image motion, pixels per frame, of the surface seen at each
        pixel of frame i (each box moved rigidly from frame i to i + 1; the last frame uses the
        step from the one before)."""
        n = self.config.n_frames
        j = i + 1 if i + 1 < n else i - 1
        sign = 1.0 if j > i else -1.0
        grid, intr = self._grid, self._grid.intr
        H, W = t.shape
        ray = np.empty((H, W, 3))
        ray[..., 0] = grid.a[None, :]
        ray[..., 1] = grid.b[:, None]
        ray[..., 2] = 1.0
        X = ray * t[..., None]
        Ri, ci, Rj, cj = self._R_wc[i], self._centres[i], self._R_wc[j], self._centres[j]
        flow = np.zeros((H * W, 2), dtype=np.float32)
        X = X.reshape(-1, 3)
        # The pixels of each box in row-major order, from one stable sort (as _shade does; a
        # comparison of the whole image per box took most of the time).
        flat = box.ravel()
        order = np.argsort(flat, kind="stable")
        keys = flat[order]
        cuts = np.flatnonzero(np.diff(keys)) + 1
        for start, stop in zip(np.r_[0, cuts], np.r_[cuts, keys.size]):
            idx = order[start:stop]
            bx = self._boxes[keys[start]]
            Rrel = bx.R[j] @ bx.R[i].T
            A = Rj.T @ Rrel @ Ri
            off = Rj.T @ (Rrel @ (ci - bx.centre[i]) + bx.centre[j] - cj)
            Xp = X[idx] @ A.T + off
            z = np.maximum(Xp[:, 2], 1e-3)
            u = intr.fx * Xp[:, 0] / z + intr.cx
            v = intr.fy * Xp[:, 1] / z + intr.cy
            ys, xs = np.divmod(idx, W)
            flow[idx] = (sign * np.column_stack([u - xs, v - ys])).astype(np.float32)
        return flow.reshape(H, W, 2)

    def _apply_effects(self, i: int, image: np.ndarray, t: np.ndarray, box: np.ndarray):
        """Frame i's image with the recipe's effects, in order: motion blur (the image averaged
        along each pixel's exact motion over the shutter), exposure gain, sensor noise (Gaussian
        plus shot noise), JPEG compression. Depth, masks and ids are untouched."""
        fx = self.recipe["effects"]
        img = image.astype(np.float32)
        if "motion_blur" in fx:
            d = self._flow(i, t, box) * np.float32(fx["motion_blur"]["shutter"])
            length = np.linalg.norm(d, axis=2)
            taps = int(np.clip(np.ceil(np.percentile(length, 99)) + 1, 2, 12))
            H, W = t.shape
            xs = np.arange(W, dtype=np.float32)[None, :]
            ys = np.arange(H, dtype=np.float32)[:, None]
            acc = np.zeros_like(img)
            for tau in np.linspace(-0.5, 0.5, taps, dtype=np.float32):
                acc += cv2.remap(img, xs + tau * d[..., 0], ys + tau * d[..., 1],
                                 cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            img = acc / np.float32(taps)
        if "exposure" in fx:
            img = img * np.float32(self._gain[i])
        if "noise" in fx:
            rng = np.random.default_rng([self.config.seed, 5, i])
            var = fx["noise"]["sigma"] ** 2 + fx["noise"]["shot"] * np.maximum(img, 0.0)
            img = img + rng.standard_normal(img.shape, dtype=np.float32) * np.sqrt(var)
        out = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        if "jpeg" in fx:
            ok, buf = cv2.imencode(".jpg", cv2.cvtColor(out, cv2.COLOR_RGB2BGR),
                                   [cv2.IMWRITE_JPEG_QUALITY, int(fx["jpeg"]["quality"])])
            if not ok:
                raise MonaVoError("synthetic scene: cv2.imencode failed on a JPEG effect")
            out = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        return out

    # -- description --------------------------------------------------------------------------

    def describe(self) -> dict:
        """What this scene is, for per-seed tables: preset, seed, field of view (deg), camera
        path, movers (kind:behaviour), effects, texture styles, mask coverage (mean and max over
        frames, fraction of frames with a mover), path length (m) and median rotation per frame
        (deg). The coverage is ray-cast at full size (no texturing)."""
        cov = self.coverage()
        poses = self._poses
        rot = [rotation_angle_deg(relative_pose(a, b)[:3, :3]) for a, b in zip(poses[:-1], poses[1:])]
        styles: dict[str, int] = {}
        for *_, style in self._materials:
            styles[style.label] = styles.get(style.label, 0) + 1
        recipe = self.recipe or {}
        camera = recipe.get("camera", {"fast-rotation": "fast-rotation"}.get(
            self.config.preset, "street-walk"))
        movers = (recipe["movers"] if recipe else
                  [(k, "legacy") for k in self.mover_kinds])
        return {"preset": self.config.preset, "seed": self.config.seed,
                "hfov_deg": float(np.degrees(self._hfov)), "camera": camera,
                "movers": [f"{k}:{b}" for k, b in movers],
                "effects": dict(recipe.get("effects", {})), "textures": styles,
                "coverage_mean": float(cov.mean()), "coverage_max": float(cov.max()),
                "frames_with_mover": float(np.mean(cov > 0)),
                "path_m": self.path_length(), "rot_deg_per_frame": float(np.median(rot))}


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

    ``root/training/<pass>/<seq>/frame_%04d.png`` (numbered from 1; the ``clean`` pass gets the
    image before the image effects of the ``mixed`` preset, every other pass the final image;
    without effects they are the same), ``root/training/camdata_left/<seq>/frame_%04d.cam``,
    ``root/training/depth/<seq>/frame_%04d.dpt`` and ``root/training/moving_masks/<seq>/
    frame_%04d.png`` (8-bit, 255 on movers, 0 elsewhere). Each file is written atomically.
    """
    root = Path(root)
    train = root / "training"
    for frame in scene:
        name = f"frame_{frame.index + 1:04d}"
        for p in passes:
            clean = p == "clean" and frame.image_clean is not None
            _write_png(train / p / seq / f"{name}.png", frame.image_clean if clean else frame.image)
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


def describe_seeds(preset: str, seeds: Sequence[int], **config) -> list[dict]:
    """:meth:`SyntheticScene.describe` of each seed of ``preset`` (other SceneConfig fields in
    ``config``): the per-seed table others read their results against."""
    return [SyntheticScene(SceneConfig(preset=preset, seed=int(s), **config)).describe()
            for s in seeds]


def describe_table(rows: Sequence[dict]) -> str:
    """A Markdown table of :func:`describe_seeds` rows."""
    def fx(e):
        short = {"motion_blur": "blur {shutter}", "noise": "noise {sigma}",
                 "exposure": "exposure +-{amplitude}", "jpeg": "jpeg q{quality}"}
        return ", ".join(short[k].format(**v) for k, v in e.items()) or "-"

    lines = ["| seed | hfov (deg) | camera | path (m) | rot (deg/frame) | movers | effects | "
             "textures | mask mean / max (%) | frames with mover (%) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        tex = ", ".join(f"{k} {v}" for k, v in sorted(r["textures"].items()))
        lines.append(f"| {r['seed']} | {r['hfov_deg']:.0f} | {r['camera']} | {r['path_m']:.2f} | "
                     f"{r['rot_deg_per_frame']:.2f} | {', '.join(r['movers'])} | {fx(r['effects'])} | "
                     f"{tex} | {100 * r['coverage_mean']:.1f} / {100 * r['coverage_max']:.1f} | "
                     f"{100 * r['frames_with_mover']:.0f} |")
    return "\n".join(lines)


def _parse_seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    return out


if __name__ == "__main__":   # python -m data_tools.synthetic --preset mixed --seeds 0-5,100-111
    import argparse

    ap = argparse.ArgumentParser(description="Per-seed table of what a generator preset samples.")
    ap.add_argument("--preset", default="mixed", choices=list(PRESETS))
    ap.add_argument("--seeds", default="0-5,100-111", help="e.g. 0-5,100-111")
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--size", default="1024x436", help="WIDTHxHEIGHT")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    print(describe_table(describe_seeds(args.preset, _parse_seeds(args.seeds), width=w, height=h,
                                        n_frames=args.frames)))
