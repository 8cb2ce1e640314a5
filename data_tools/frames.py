"""Input frames: a folder of images or a video file, streamed one :class:`Frame` at a time.

Every input is validated when it is opened (missing path, unknown kind, no images, mixed sizes,
undecodable video, fewer than two frames), so a run fails in its first second with one line naming
the file, not after an hour. Images are decoded only while iterating and never all held at once.

Images are RGB here (OpenCV decodes BGR; the conversion happens in this module and nowhere else).
"""
from __future__ import annotations

import contextlib
import itertools
import logging
import math
import os
import re
import sys
import tempfile
import warnings
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from data_tools.atomic import write_bytes_atomic
from mona_vo.errors import ConfigError, InputError

log = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".webm")


@dataclass(frozen=True, eq=False)  # eq=False: comparing frames would compare whole images
class Frame:
    """One input frame."""

    index: int  # 0-based position in the whole input, before stride/max_frames
    timestamp: float  # seconds, frame number or index: see FrameSource.timestamp_kind
    name: str  # file stem ('00012', 'frame_0001', '1548339827.58438'); video: f'{index:06d}'
    image: np.ndarray  # (H, W, 3) uint8 RGB


def read_ahead(frames, n: int) -> tuple[list, Iterator]:
    """The first ``n`` frames of a stream, and the whole stream again (those frames replayed
    before the rest): how a stage that must see the head of a clip first (the focal-length
    estimate, the letterbox test) keeps a one-pass input (a video, an iterator) whole."""
    it = iter(frames)
    head = list(itertools.islice(it, n))
    return head, itertools.chain(head, it)


def natural_key(name: str) -> tuple:
    """Sort key ordering digit runs by value, so 'frame_2' < 'frame_10'."""
    parts = re.split(r"(\d+)", name)
    # (0, number) for digit runs and (1, text) otherwise keeps ints and strs from being compared.
    return tuple((0, int(p), "") if p.isdigit() else (1, 0, p.lower()) for p in parts if p), name


def timestamps_from_names(names: Sequence[str]) -> tuple[list[float], str]:
    """Timestamps of frames from their file stems, and their kind.

    'seconds' when every stem is a decimal number with a '.' (TUM '1548339827.58438');
    'frame_number' when every stem ends in digits ('frame_0001' -> 1, '00012' -> 12);
    otherwise 'index' (0, 1, 2, ...). A kind is used only if it gives strictly increasing values
    in the given order, because evaluation associates poses by timestamp and needs them unique.
    """
    candidates = []
    if all(is_decimal_stem(n) for n in names):
        candidates.append(([float(n) for n in names], "seconds"))
    trailing = [re.search(r"(\d+)$", n) for n in names]
    if all(trailing):
        candidates.append(([float(m.group(1)) for m in trailing], "frame_number"))
    for values, kind in candidates:
        if all(a < b for a, b in zip(values, values[1:])):
            return values, kind
    return [float(i) for i in range(len(names))], "index"


def is_decimal_stem(name: str) -> bool:
    """True for stems like '1548339827.58438' (digits, a point, digits)."""
    return re.fullmatch(r"\d+\.\d+", name) is not None


def _selected(n: int, stride: int, max_frames: int | None) -> range:
    """Positions in the input kept by stride and max_frames."""
    r = range(0, n, stride)
    return r if max_frames is None else r[:max_frames]


def _check_stride(stride: int, max_frames: int | None) -> None:
    # ConfigError, not ValueError: these come straight from --stride / --max-frames.
    if not isinstance(stride, int) or stride < 1:
        raise ConfigError(f"stride must be a positive integer, got {stride!r}")
    if max_frames is not None and (not isinstance(max_frames, int) or max_frames < 1):
        raise ConfigError(f"max_frames must be a positive integer or None, got {max_frames!r}")


def _too_few(path: Path, n: int, selected: int) -> InputError:
    what = f"{n} frame{'s' if n != 1 else ''}"
    if selected != n:
        what += f", {selected} after stride/max_frames"
    return InputError(f"{path}: only {what}; a camera trajectory needs at least 2 frames")


@contextlib.contextmanager
def native_stderr_to_log(what: str):
    """Send what C libraries print on file descriptor 2 (libpng's "PNG input buffer is incomplete",
    FFmpeg's "moov atom not found", OpenCV's own [ERROR] lines) to this module's log instead.

    Errors are reported by the caller as one line naming the file; the libraries' own chatter,
    printed once per bad frame, would bury it. With ``-v`` the captured text is logged as INFO.
    """
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):  # no real stderr (e.g. an embedding host)
        yield
        return
    sys.stderr.flush()
    saved = os.dup(fd)
    try:
        with tempfile.TemporaryFile() as sink:
            os.dup2(sink.fileno(), fd)
            try:
                yield
            finally:
                os.dup2(saved, fd)
                sink.seek(0)
                text = sink.read(4096).decode("utf-8", "replace").strip()
                if text:
                    log.info("%s: %s", what, " | ".join(text.splitlines()))
    finally:
        os.close(saved)


def _cv2_reason(exc: Exception) -> str:
    """The one-line gist of a cv2.error ('pixels <= CV_IO_MAX_IMAGE_PIXELS' rather than the path
    of OpenCV's source file)."""
    text = " ".join(str(exc).split())
    m = re.search(r"error: \([^)]*\) (.*?)(?: in function .*)?$", text)
    return m.group(1) if m else text


def bgr_to_rgb(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 OpenCV BGR -> RGB (a new array)."""
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def decode_file(path: Path, flags: int, what: str = "image") -> np.ndarray:
    """cv2.imdecode of a file's bytes with ``flags``. Raises InputError naming the file (and
    ``what`` it should hold) when it cannot be read or decoded (e.g. a truncated PNG)."""
    try:
        data = np.frombuffer(path.read_bytes(), np.uint8)
    except OSError as exc:
        raise InputError(f"{path}: cannot read {what} ({exc.strerror or exc})") from None
    # imdecode on bytes rather than imread: same decoder, but a read failure and a decode failure
    # get different messages, and non-ASCII paths work on every platform.
    out = None
    if data.size:
        with native_stderr_to_log(str(path)):
            try:
                out = cv2.imdecode(data, flags)
            except cv2.error as exc:  # e.g. a header announcing more pixels than OpenCV allows
                raise InputError(f"{path}: cannot decode {what} ({_cv2_reason(exc)})") from None
    if out is None:
        raise InputError(f"{path}: cannot decode {what} (truncated, corrupt or not an image)")
    return out


def decode_image(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of an image file; grey images are repeated over 3 channels.

    Raises InputError naming the file when it cannot be read or decoded (e.g. a truncated PNG).
    """
    # EXIF orientation is ignored so that the decoded size is the header's (image_size), which
    # sizes the input.
    return bgr_to_rgb(decode_file(path, cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION))


def write_image(path: str | os.PathLike, image_rgb: np.ndarray) -> None:
    """Write (H, W, 3) uint8 RGB or (H, W) uint8 grey as an image (format from the suffix), atomically."""
    image = np.asarray(image_rgb)
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        raise ValueError(f"image must be (H, W, 3) or (H, W) uint8, got {image.shape} {image.dtype}")
    path = Path(path)
    bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image
    ok, buf = cv2.imencode(path.suffix or ".png", bgr)
    if not ok:
        raise ValueError(f"OpenCV cannot encode an image as {path.suffix!r}")
    write_bytes_atomic(path, buf.tobytes())


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the image header only (cheap: no pixel decoding)."""
    try:
        # PIL warns (corrupt EXIF, DecompressionBombWarning) on stderr; the size is all we need.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(path) as im:
                w, h = im.size
    except FileNotFoundError:
        raise InputError(f"{path}: image not found") from None
    except (UnidentifiedImageError, OSError) as exc:
        raise InputError(f"{path}: not a readable image ({exc})") from None
    except Exception as exc:  # noqa: BLE001 -- PIL's header parsers raise anything on garbage
        # (DecompressionBombError for an absurd size, ValueError, SyntaxError, struct.error, ...)
        raise InputError(f"{path}: not a readable image ({type(exc).__name__}: {exc})") from None
    if w < 1 or h < 1:
        raise InputError(f"{path}: image of {w}x{h} pixels")
    return w, h


class FrameSource(ABC):
    """Frames of one input, streamed in order. Iterating again starts again from the first frame.

    Attributes: ``path`` (the folder, video or sequence), ``kind`` ('folder' | 'video'),
    ``width``, ``height`` (pixels), ``fps`` (video frame rate, None for images),
    ``timestamp_kind`` ('seconds' | 'frame_number' | 'index'), ``names`` and ``timestamps``
    (one per frame that iteration yields, after stride and max_frames).
    """

    path: Path
    kind: str
    width: int
    height: int
    fps: float | None
    timestamp_kind: str
    names: list[str]
    timestamps: list[float]

    @abstractmethod
    def __len__(self) -> int:
        """Number of frames iteration yields (after stride and max_frames)."""

    @abstractmethod
    def __iter__(self) -> Iterator[Frame]:
        """Frames in order, decoded one at a time."""

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({str(self.path)!r}, {len(self)} frames, "
                f"{self.width}x{self.height}, timestamps: {self.timestamp_kind})")


class ImageFiles(FrameSource):
    """Frames from a list of image files (a folder, or a dataset's frame list).

    ``files`` are in playback order; ``timestamps`` (one per file, of kind ``timestamp_kind``,
    'seconds' unless told) default to those inferred from the file stems by
    :func:`timestamps_from_names`. Every selected file's size is read from its
    header here, so mixed sizes fail at open, not mid-run.
    """

    kind = "folder"
    fps = None

    def __init__(self, files: Sequence[Path], *, path: Path, timestamps: Sequence[float] | None = None,
                 timestamp_kind: str | None = None, stride: int = 1, max_frames: int | None = None):
        _check_stride(stride, max_frames)
        files = [Path(f) for f in files]
        self.path = Path(path)
        if not files:
            raise InputError(f"{self.path}: no images ({', '.join(IMAGE_EXTENSIONS)})")
        names = [f.stem for f in files]
        if timestamps is None:
            timestamps, timestamp_kind = timestamps_from_names(names)
        elif len(timestamps) != len(files):
            raise ValueError(f"{len(timestamps)} timestamps for {len(files)} files")
        self.timestamp_kind = timestamp_kind or "seconds"
        keep = _selected(len(files), stride, max_frames)
        if len(keep) < 2:
            raise _too_few(self.path, len(files), len(keep))
        self._indices = list(keep)
        self.files = [files[i] for i in keep]
        self.names = [names[i] for i in keep]
        self.timestamps = [float(timestamps[i]) for i in keep]
        self.width, self.height = image_size(self.files[0])
        for f in self.files[1:]:
            size = image_size(f)
            if size != (self.width, self.height):
                raise InputError(
                    f"{self.path}: image sizes differ: {f.name} is {size[0]}x{size[1]} but "
                    f"{self.files[0].name} is {self.width}x{self.height}")

    def __len__(self) -> int:
        return len(self.files)

    def __iter__(self) -> Iterator[Frame]:
        for index, f, name, t in zip(self._indices, self.files, self.names, self.timestamps):
            image = decode_image(f)
            if image.shape[:2] != (self.height, self.width):
                raise InputError(f"{f}: image is {image.shape[1]}x{image.shape[0]} but the input is "
                                 f"{self.width}x{self.height} (file changed after opening?)")
            yield Frame(index, t, name, image)


class VideoFrames(FrameSource):
    """Frames decoded from a video file with ``cv2.VideoCapture``; timestamp = frame index.

    ``len()`` comes from the container's frame count (CAP_PROP_FRAME_COUNT), which some files
    report approximately: iteration stops at the first frame that cannot be decoded, so it may yield
    a few frames fewer than ``len()`` (logged as a warning). ``names`` and ``timestamps`` follow
    ``len()``.
    """

    kind = "video"
    timestamp_kind = "index"

    def __init__(self, path: Path, *, stride: int = 1, max_frames: int | None = None):
        _check_stride(stride, max_frames)
        self.path = Path(path)
        self._stride = stride
        with native_stderr_to_log(str(self.path)):
            self._probe(stride, max_frames)
        self.names = [f"{i:06d}" for i in self._indices]
        self.timestamps = [float(i) for i in self._indices]

    def _probe(self, stride: int, max_frames: int | None) -> None:
        cap = cv2.VideoCapture(str(self.path))
        try:
            if not cap.isOpened():
                raise InputError(f"{self.path}: cannot open video (corrupt file or a container or "
                                 "codec this OpenCV build does not support)")
            count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            fps = cap.get(cv2.CAP_PROP_FPS)
            self.fps = float(fps) if fps and math.isfinite(fps) and fps > 0 else None
            ok, first = cap.read()
            if not ok or first is None:
                raise InputError(f"{self.path}: no decodable frame (empty or corrupt video, or a "
                                 "codec this OpenCV build does not support)")
            self.height, self.width = first.shape[:2]
            if count < 2:
                # The container does not say (some streams) or says 1: count by grabbing, once.
                count = 1
                while cap.grab():
                    count += 1
        finally:
            cap.release()
        self._indices = list(_selected(count, stride, max_frames))
        if len(self._indices) < 2:
            raise _too_few(self.path, count, len(self._indices))

    def __len__(self) -> int:
        return len(self._indices)

    def __iter__(self) -> Iterator[Frame]:
        with native_stderr_to_log(str(self.path)):
            cap = cv2.VideoCapture(str(self.path))
        yielded = 0
        try:
            for k, index in enumerate(self._indices):
                with native_stderr_to_log(str(self.path)):
                    if k > 0:
                        for _ in range(self._stride - 1):  # grab() skips without converting
                            if not cap.grab():
                                break
                    ok, bgr = cap.read()
                if not ok or bgr is None:
                    break
                if bgr.shape[:2] != (self.height, self.width):
                    raise InputError(f"{self.path}: frame {index} is {bgr.shape[1]}x{bgr.shape[0]} "
                                     f"but the first frame is {self.width}x{self.height}")
                yielded += 1
                yield Frame(index, float(index), f"{index:06d}", bgr_to_rgb(bgr))
        finally:
            cap.release()
        if yielded < len(self):
            # Containers may announce a frame or two more than they hold; more than that is a
            # truncated or damaged file, and a trajectory of its first part would be silently short.
            if yielded < 2 or len(self) - yielded > max(2, len(self) // 100):
                raise InputError(f"{self.path}: decoding stopped after {yielded} of the {len(self)} "
                                 "frames the container announces (truncated or corrupt video)")
            log.warning("%s: decoded %d frames, the container announced %d (after stride)",
                        self.path, yielded, len(self))


def list_images(folder: Path) -> list[Path]:
    """Image files directly in ``folder``, in natural name order (hidden files skipped)."""
    # Hidden files are skipped because macOS leaves '._name.png' resource files beside images.
    files = [p for p in folder.iterdir()
             if p.suffix.lower() in IMAGE_EXTENSIONS and not p.name.startswith(".") and p.is_file()]
    return sorted(files, key=lambda p: natural_key(p.name))


def open_frames(path: str | os.PathLike, *, stride: int = 1, max_frames: int | None = None) -> FrameSource:
    """Open a folder of images or a video file as a validated, streamed :class:`FrameSource`.

    Folder images (``IMAGE_EXTENSIONS``) play in natural name order, except when the stems are
    decimal timestamps ('seconds'), which play in time order (natural order would put .6179 before
    .58438). ``stride`` keeps every stride-th frame, ``max_frames`` caps the number kept.
    Raises InputError (one line naming the path) for anything that cannot give a trajectory.
    """
    path = Path(path)
    try:
        exists, is_dir = path.exists(), path.is_dir()
    except (OSError, ValueError) as exc:  # e.g. a name longer than the file system allows
        raise InputError(f"{path}: cannot access ({getattr(exc, 'strerror', None) or exc})") from None
    if not exists:
        raise InputError(f"{path}: no such file or folder")
    if is_dir:
        try:
            files = list_images(path)
        except OSError as exc:
            raise InputError(f"{path}: cannot list this folder ({exc.strerror or exc})") from None
        if not files:
            raise InputError(f"{path}: no images ({', '.join(IMAGE_EXTENSIONS)}) in this folder")
        if all(is_decimal_stem(f.stem) for f in files):
            # Time order, not name order: natural order puts '.6179' before '.58438'.
            files.sort(key=lambda f: float(f.stem))
        values, kind = timestamps_from_names([f.stem for f in files])
        return ImageFiles(files, path=path, timestamps=values, timestamp_kind=kind,
                          stride=stride, max_frames=max_frames)
    suffix = path.suffix.lower()
    if suffix in VIDEO_EXTENSIONS:
        return VideoFrames(path, stride=stride, max_frames=max_frames)
    if suffix in IMAGE_EXTENSIONS:
        raise InputError(f"{path}: a single image; a camera trajectory needs at least 2 frames "
                         "(pass the folder that holds the frames)")
    raise InputError(f"{path}: neither a folder of images nor a video "
                     f"({', '.join(VIDEO_EXTENSIONS)})")

