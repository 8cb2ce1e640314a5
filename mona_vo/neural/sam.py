"""``sam`` segmenter: Segment Anything (Kirillov et al., ICCV 2023), the MONA paper's segmenter,
from a local checkpoint (default ``sam_vit_b_01ec64.pth`` in ``$MONA_VO_WEIGHTS``; ViT-L and ViT-H
with ``model_type='vit_l' | 'vit_h'``).

The model is built by ``segment_anything.sam_model_registry[model_type]()`` and the state dict
read from the checkpoint on the CPU (``weights_only``), then moved to ``device``. The image
embedding (the costly ViT pass) is computed once per frame: repeated calls on the same image reuse
it (the frame is recognised by a hash of its pixels).

Prompts, in the pixel convention of :mod:`mona_vo.conventions` (pixel centres at integers):

* boxes (the method, and the raw-boxes ablation): one batched decoder call, one mask per box
  (``multimask_output=False``: a box is not ambiguous), the masks united. SAM reads a box as the
  pixel indices of its first and last row and column (its prompt encoder adds 0.5 to reach pixel
  centres in its own corner-origin frame), so the box ``(x0, y0, x1, y1)`` of
  :class:`~mona_vo.detection.Boxes` (pixel edges) is passed as ``(x0 + 0.5, y0 + 0.5, x1 - 0.5,
  y1 - 0.5)``.
* points only (the paper's points ablation): each point is its own positive prompt (a point may
  sit on any of several movers), batched; SAM's three candidate masks per point are scored by its
  own IoU prediction and the best one kept; the masks are united. Points are pixel centres, which
  SAM takes unchanged.

The united mask is dilated by ``dilate_px`` (as the ``grabcut`` segmenter: a mask that feeds the
VO costs less when slightly too large than when it misses an object's rim).
"""
from __future__ import annotations

import hashlib

import cv2
import numpy as np

from mona_vo.detection import Boxes, FrameContext
from mona_vo.errors import BackendError
from mona_vo.neural import load_into, load_state_dict, require, torch_device
from mona_vo.neural.weights import resolve_checkpoint
from mona_vo.segmentation import Segmenter

MODEL_TYPES = ("vit_b", "vit_l", "vit_h")


def _fingerprint(image: np.ndarray) -> tuple:
    return image.shape, hashlib.blake2b(np.ascontiguousarray(image).data, digest_size=16).digest()


class SamSegmenter(Segmenter):
    """Box- or point-prompted Segment Anything.

    checkpoint:   the SAM ``.pth`` (or a folder holding its documented name; default
                  ``$MONA_VO_WEIGHTS``).
    device:       'cpu' (default) or 'cuda' / 'cuda:N'.
    model_type:   'vit_b' (default), 'vit_l' or 'vit_h'; must match the checkpoint.
    dilate_px:    the united mask is dilated by this many pixels (0: SAM's mask as it is).
    max_prompts:  at most this many boxes (highest scores first) or points per frame.
    batch:        prompts per decoder call (memory bound on large images).
    """

    def __init__(self, checkpoint=None, device: str = "cpu", model_type: str = "vit_b",
                 dilate_px: int = 3, max_prompts: int = 64, batch: int = 16):
        if model_type not in MODEL_TYPES:
            raise BackendError(f"sam: model_type '{model_type}' unknown; choose one of: "
                               f"{', '.join(MODEL_TYPES)}")
        if int(dilate_px) < 0 or int(max_prompts) < 1 or int(batch) < 1:
            raise BackendError("sam: dilate_px must be >= 0, max_prompts and batch >= 1")
        what = f"SAM {model_type} segmenter"
        self.checkpoint = resolve_checkpoint(f"sam_{model_type}", checkpoint)
        self.model_type = model_type
        self.dilate_px, self.max_prompts, self.batch = int(dilate_px), int(max_prompts), int(batch)
        torch = require("torch", what)
        sa = require("segment_anything", what)
        self._torch = torch
        self.device = torch_device(device, what)
        sam = sa.sam_model_registry[model_type](checkpoint=None)
        load_into(sam, load_state_dict(self.checkpoint, what), self.checkpoint, what,
                  hint="does model_type (vit_b | vit_l | vit_h) match the file?")
        self._predictor = sa.SamPredictor(sam.eval().to(self.device))
        self._image_key = None

    # ------------------------------------------------------------------ embedding
    def _set_image(self, image: np.ndarray) -> None:
        key = _fingerprint(image)
        if key != self._image_key:
            self._predictor.set_image(np.ascontiguousarray(image), image_format="RGB")
            self._image_key = key

    # ------------------------------------------------------------------ prompts
    def _decode(self, boxes_t=None, points_t=None, labels_t=None, multimask: bool = False):
        """(B, H, W) bool masks of a batch of transformed prompts (best of 3 when multimask)."""
        masks, iou, _ = self._predictor.predict_torch(point_coords=points_t,
                                                      point_labels=labels_t, boxes=boxes_t,
                                                      multimask_output=multimask)
        if multimask:
            best = iou.argmax(dim=1)
            masks = masks[self._torch.arange(len(masks), device=masks.device), best]
        else:
            masks = masks[:, 0]
        return masks

    def _segment_boxes(self, boxes: Boxes, shape) -> np.ndarray:
        torch = self._torch
        order = np.argsort(-np.asarray(boxes.score, np.float64), kind="stable")[:self.max_prompts]
        b = np.asarray(boxes.xyxy, np.float64)[order].reshape(-1, 4)
        b = b + np.array([0.5, 0.5, -0.5, -0.5])                    # edges -> SAM pixel indices
        b[:, 2] = np.maximum(b[:, 2], b[:, 0])
        b[:, 3] = np.maximum(b[:, 3], b[:, 1])
        acc = torch.zeros(shape, dtype=torch.bool, device=self.device)
        for i in range(0, len(b), self.batch):
            t = torch.as_tensor(b[i:i + self.batch], dtype=torch.float32, device=self.device)
            t = self._predictor.transform.apply_boxes_torch(t, shape)
            acc |= self._decode(boxes_t=t).any(dim=0)
        return acc.cpu().numpy()

    def _segment_points(self, points: np.ndarray, shape) -> np.ndarray:
        torch = self._torch
        p = points[:self.max_prompts]
        acc = torch.zeros(shape, dtype=torch.bool, device=self.device)
        for i in range(0, len(p), self.batch):
            t = torch.as_tensor(p[i:i + self.batch, None, :], dtype=torch.float32,
                                device=self.device)                 # (B, 1, 2): one point each
            t = self._predictor.transform.apply_coords_torch(t, shape)
            labels = torch.ones(t.shape[:2], dtype=torch.int64, device=self.device)
            acc |= self._decode(points_t=t, labels_t=labels, multimask=True).any(dim=0)
        return acc.cpu().numpy()

    def segment(self, image: np.ndarray, boxes: Boxes | None = None,
                points: np.ndarray | None = None,
                context: FrameContext | None = None) -> np.ndarray:
        image = np.asarray(image)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"sam needs an (H, W, 3) uint8 RGB image, got {image.shape} "
                             f"{image.dtype}")
        H, W = image.shape[:2]
        has_boxes = boxes is not None and len(boxes) > 0
        pts = np.zeros((0, 2)) if points is None else np.asarray(points, np.float64).reshape(-1, 2)
        pts = pts[np.isfinite(pts).all(axis=1)]
        if not has_boxes and len(pts) == 0:
            return np.zeros((H, W), bool)
        self._set_image(image)
        with self._torch.inference_mode():
            if has_boxes:
                mask = self._segment_boxes(boxes, (H, W))
            else:
                mask = self._segment_points(pts, (H, W))
        if self.dilate_px > 0 and mask.any():
            k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE,
                                          (2 * self.dilate_px + 1, 2 * self.dilate_px + 1))
            mask = cv2.dilate(mask.astype(np.uint8), k) > 0
        return np.asarray(mask, bool)
