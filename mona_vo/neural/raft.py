"""``raft`` flow: torchvision's RAFT (Teed and Deng, ECCV 2020), the network the MONA paper uses.

The model is built with ``weights=None`` (torchvision never downloads) and its state dict is read
from the local checkpoint (:mod:`mona_vo.neural.weights`: ``raft_large_C_T_SKHT_V2-ff5fadd5.pth``,
or ``raft_small_C_T_V2-01064c6d.pth`` with ``model='small'``, both torchvision's own files).

Per pair: RGB uint8 -> float in [-1, 1] (torchvision's ``OpticalFlow`` preset), both images padded
by edge replication to multiples of 8 and to at least 128 x 128 (RAFT's feature maps are 1/8 of
the input and its correlation pyramid halves them 3 times; the padding is split evenly between
the two sides, as in RAFT's own ``InputPadder``), the last of
``iterations`` refinements taken, the padding cropped off.

Sign convention: RAFT returns ``coords1 - coords0``, where ``coords0`` is the pixel grid of the
first image and ``coords1`` where those pixels are found in the second; channel 0 is x (columns),
channel 1 is y (rows). So, as :meth:`mona_vo.flow.Flow.compute` requires, the pixel (x, y) of
``image0`` is seen at ``(x + u, y + v)`` in ``image1``. Displacements do not depend on where the
pixel origin is put, so the pixel-centre convention of :mod:`mona_vo.conventions` needs no shift.
"""
from __future__ import annotations

import numpy as np

from mona_vo.errors import BackendError
from mona_vo.flow import Flow
from mona_vo.neural import load_into, load_state_dict, require, torch_device
from mona_vo.neural.weights import resolve_checkpoint

MODELS = ("large", "small")
MIN_SIDE = 128   # pixels: torchvision RAFT's smallest input side (4 pyramid levels of 1/8 maps)


class RaftFlow(Flow):
    """Dense flow from torchvision RAFT.

    checkpoint:  path of the torchvision state dict (file or folder; default: the documented file
                 in ``$MONA_VO_WEIGHTS``).
    device:      'cpu' (default) or 'cuda' / 'cuda:N'.
    model:       'large' (default, raft_large) or 'small' (raft_small).
    iterations:  refinement iterations (torchvision's default 12; the paper's RAFT uses 12-32).
    """

    def __init__(self, checkpoint=None, device: str = "cpu", model: str = "large",
                 iterations: int = 12):
        if model not in MODELS:
            raise BackendError(f"raft: model '{model}' unknown; choose one of: {', '.join(MODELS)}")
        if int(iterations) < 1:
            raise BackendError("raft: iterations must be at least 1")
        what = f"RAFT-{model} flow"
        self.checkpoint = resolve_checkpoint(f"raft_{model}", checkpoint)
        self.model_name = model
        self.iterations = int(iterations)
        torch = require("torch", what)
        optical_flow = require("torchvision.models.optical_flow", what)
        self._torch = torch
        self.device = torch_device(device, what)
        build = optical_flow.raft_large if model == "large" else optical_flow.raft_small
        net = build(weights=None, progress=False)
        load_into(net, load_state_dict(self.checkpoint, what), self.checkpoint, what,
                  hint=f"is it torchvision's raft_{model} file (model='large'|'small')?")
        self._model = net.eval().to(self.device)

    def _to_tensor(self, image: np.ndarray):
        """(1, 3, H, W) float32 in [-1, 1] on the device, from (H, W, 3) uint8 RGB."""
        image = np.asarray(image)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"raft needs (H, W, 3) uint8 RGB images, got {image.shape} "
                             f"{image.dtype}")
        t = self._torch.from_numpy(np.ascontiguousarray(image)).to(self.device)
        return (t.permute(2, 0, 1)[None].float() / 127.5 - 1.0).contiguous()

    @staticmethod
    def padding(height: int, width: int) -> tuple[int, int, int, int]:
        """(left, right, top, bottom) pixels that bring height and width to multiples of 8 and at
        least :data:`MIN_SIDE` (RAFT's correlation pyramid needs 1/8 feature maps of 16 or more)."""
        ph = max(height + (-height) % 8, MIN_SIDE) - height
        pw = max(width + (-width) % 8, MIN_SIDE) - width
        return pw // 2, pw - pw // 2, ph // 2, ph - ph // 2

    def compute(self, image0: np.ndarray, image1: np.ndarray) -> np.ndarray:
        if np.shape(image0) != np.shape(image1):
            raise ValueError(f"flow needs two images of one size, got {np.shape(image0)} and "
                             f"{np.shape(image1)}")
        torch = self._torch
        height, width = image0.shape[:2]
        left, right, top, bottom = self.padding(height, width)
        with torch.inference_mode():
            pair = torch.cat([self._to_tensor(image0), self._to_tensor(image1)])
            if left or right or top or bottom:
                pair = torch.nn.functional.pad(pair, (left, right, top, bottom), mode="replicate")
            flow = self._model(pair[:1], pair[1:], num_flow_updates=self.iterations)[-1]
            flow = flow[0, :, top:top + height, left:left + width]
            out = flow.permute(1, 2, 0).float().cpu().numpy()
        return np.ascontiguousarray(out, dtype=np.float32)
