"""``yolo`` detector: an Ultralytics YOLO checkpoint (the MONA paper's detector), loaded from a local
file (default ``yolo11n.pt`` in ``$MONA_VO_WEIGHTS``; any Ultralytics detection ``.pt`` works).

Ultralytics is imported when the detector is built, with ``YOLO_OFFLINE=1`` set unless the caller
set it (no online checks, no asset downloads). Note that Ultralytics itself writes a settings file
under its config folder on first import; set ``YOLO_CONFIG_DIR`` to choose that folder.

Boxes: Ultralytics returns ``xyxy`` in the "top-left pixel spans [0, 1]" convention of the input
image; :class:`mona_vo.detection.Boxes` puts pixel centres at integers, so 0.5 is subtracted from
every coordinate and the boxes are clipped to ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``. Labels are the
checkpoint's class names; scores its confidences.

Class filter (COCO ids, as in every official YOLO checkpoint): ``people`` = {0 person},
``vehicles`` = {1 bicycle, 2 car, 3 motorcycle, 4 airplane, 5 bus, 6 train, 7 truck, 8 boat},
``animals`` = {14 bird .. 23 giraffe}. The default keeps all three groups: the things that move.
"""
from __future__ import annotations

import os
from typing import Iterable

import numpy as np

from mona_vo.detection import Boxes, Detector, FrameContext
from mona_vo.errors import BackendError
from mona_vo.neural import require, torch_device
from mona_vo.neural.weights import resolve_checkpoint

# COCO class ids (0-based, as YOLO numbers them) of the groups that can move on their own.
COCO_GROUPS: dict[str, tuple[int, ...]] = {
    "people": (0,),
    "vehicles": (1, 2, 3, 4, 5, 6, 7, 8),
    "animals": tuple(range(14, 24)),
}
DEFAULT_CLASSES = ("people", "vehicles", "animals")


class YoloDetector(Detector):
    """Boxes from an Ultralytics YOLO detection checkpoint.

    checkpoint:  the ``.pt`` file (or a folder holding ``yolo11n.pt``; default ``$MONA_VO_WEIGHTS``).
    device:      'cpu' (default) or 'cuda' / 'cuda:N'.
    classes:     what to keep: group names (``people``, ``vehicles``, ``animals``: COCO ids above),
                 class names of the checkpoint (e.g. ``'dog'``) or integer class ids; None keeps
                 every class. Default: the three groups.
    conf:        minimum confidence of a box, in [0, 1].
    iou:         IoU threshold of YOLO's non-maximum suppression, in [0, 1].
    imgsz:       inference size, pixels (the longer side; YOLO letterboxes to it).
    max_det:     at most this many boxes per image.
    """

    def __init__(self, checkpoint=None, device: str = "cpu",
                 classes: Iterable[str | int] | None = DEFAULT_CLASSES, conf: float = 0.25,
                 iou: float = 0.7, imgsz: int = 640, max_det: int = 100):
        if not 0.0 <= float(conf) <= 1.0 or not 0.0 <= float(iou) <= 1.0:
            raise BackendError("yolo: conf and iou must be in [0, 1]")
        if int(imgsz) < 32 or int(max_det) < 1:
            raise BackendError("yolo: imgsz must be at least 32 pixels and max_det at least 1")
        what = "YOLO detector"
        self.checkpoint = resolve_checkpoint("yolo", checkpoint)
        os.environ.setdefault("YOLO_OFFLINE", "1")
        ultralytics = require("ultralytics", what)
        self.device = torch_device(device, what)
        # Ultralytics' own device string: 'cpu' or 'cuda:N' (it reads 'cuda:N' as GPU N).
        self._device_arg = ("cpu" if self.device.type == "cpu"
                            else f"cuda:{0 if self.device.index is None else self.device.index}")
        try:
            self._model = ultralytics.YOLO(str(self.checkpoint), task="detect")
        except Exception as exc:  # noqa: BLE001 - ultralytics raises many kinds on a bad file
            raise BackendError(f"{what}: cannot load checkpoint {self.checkpoint} "
                               f"({type(exc).__name__}: {str(exc).splitlines()[0]})") from None
        self.names: dict[int, str] = {int(k): str(v) for k, v in self._model.names.items()}
        self.class_ids = None if classes is None else self._class_ids(classes)
        self.conf, self.iou = float(conf), float(iou)
        self.imgsz, self.max_det = int(imgsz), int(max_det)

    def _class_ids(self, classes: Iterable[str | int]) -> list[int]:
        by_name = {v: k for k, v in self.names.items()}
        ids: set[int] = set()
        for c in ([classes] if isinstance(classes, (str, int)) else classes):
            if isinstance(c, (int, np.integer)):
                ids.add(int(c))
            elif c in COCO_GROUPS:
                ids.update(COCO_GROUPS[c])
            elif c in by_name:
                ids.add(by_name[c])
            else:
                raise BackendError(f"yolo: class '{c}' is neither a group "
                                   f"({', '.join(COCO_GROUPS)}) nor a class of {self.checkpoint.name}")
        return sorted(ids)

    def detect(self, image: np.ndarray, context: FrameContext | None = None) -> Boxes:
        image = np.asarray(image)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"yolo needs an (H, W, 3) uint8 RGB image, got {image.shape} "
                             f"{image.dtype}")
        H, W = image.shape[:2]
        bgr = np.ascontiguousarray(image[..., ::-1])   # Ultralytics reads numpy images as BGR
        result = self._model.predict(bgr, conf=self.conf, iou=self.iou, imgsz=self.imgsz,
                                     max_det=self.max_det, classes=self.class_ids,
                                     device=self._device_arg, verbose=False)[0]
        det = result.boxes
        if det is None or len(det) == 0:
            return Boxes.empty()
        xyxy = det.xyxy.float().cpu().numpy().astype(np.float32).reshape(-1, 4) - 0.5
        score = det.conf.float().cpu().numpy().astype(np.float32)
        cls = det.cls.cpu().numpy().astype(np.int64)
        label = np.array([self.names.get(int(c), str(int(c))) for c in cls])
        return Boxes(xyxy, score, label).clipped(W, H)
