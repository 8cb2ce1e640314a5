"""End-point error of a flow back end on one image pair with ground-truth flow (``mona-vo eval flow``).

The back end is the one the mask pipeline builds (:data:`mona_vo.flow.FLOWS`; ``dis`` with the
pipeline's default :class:`~mona_vo.flow.DISFlowConfig`, neural ones with a device and a
checkpoint). Conventions of MPI Sintel's evaluation:

- end-point error of a pixel: ``||u_est(x) - u_gt(x)||``, pixels;
- ``epe_all``: mean over every pixel not marked invalid (Sintel's ``invalid/`` PNG, non-zero =
  invalid; without the file every pixel counts);
- ``epe_noc``: mean over the valid pixels that are not occluded (Sintel's ``occlusions/`` PNG,
  non-zero = occluded in the second frame; without the file ``epe_noc`` equals ``epe_all``);
- ``ms_per_pair``: median wall time of ``repeats`` calls of ``Flow.compute`` after one warm-up
  call, milliseconds (resizes inside the back end included, file reading not).

:func:`end_point_error` is the maths (numpy only); :func:`evaluate_flow` reads the files through
``data_tools`` and times the back end.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from mona_vo.errors import EvalError


@dataclass(frozen=True)
class FlowEvalResult:
    """Errors of one back end on one pair (module docstring for the definitions)."""

    flow: str                   # back-end name (mona_vo.flow.FLOWS)
    epe_noc: float              # mean end-point error, valid non-occluded pixels, px
    epe_all: float              # mean end-point error, all valid pixels, px
    ms_per_pair: float          # median time of one Flow.compute call, ms
    n_noc: int                  # pixels behind epe_noc
    n_all: int                  # pixels behind epe_all
    width: int                  # image width, px
    height: int                 # image height, px
    gt_mean_magnitude: float    # mean length of the GT flow over the valid pixels, px
    repeats: int                # timed calls behind ms_per_pair

    def to_dict(self) -> dict:
        return asdict(self)


def end_point_error(flow: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None) -> float:
    """Mean end-point error in pixels.

    flow, gt: (H, W, 2) float displacements u, v, pixels (same size).
    valid:    (H, W) bool, the pixels to average over (default all); non-finite GT vectors are
              left out as well.
    Raises EvalError when shapes differ or no pixel is left.
    """
    flow = np.asarray(flow, np.float64)
    gt = np.asarray(gt, np.float64)
    if flow.shape != gt.shape or flow.ndim != 3 or flow.shape[2] != 2:
        raise EvalError(f"flow {flow.shape} and ground truth {gt.shape} must both be (H, W, 2)")
    use = np.isfinite(gt).all(axis=2)
    if valid is not None:
        valid = np.asarray(valid, bool)
        if valid.shape != flow.shape[:2]:
            raise EvalError(f"valid mask {valid.shape} does not match the flow {flow.shape[:2]}")
        use &= valid
    if not use.any():
        raise EvalError("no pixel left to compute an end-point error over")
    err = np.linalg.norm(flow - gt, axis=2)
    return float(err[use].mean())


def build_flow(name: str, *, weights: str | None = None, device: str = "cpu"):
    """The flow back end ``name`` as the mask pipeline builds it: ``dis`` with the pipeline's
    default settings, a neural one with ``device`` and ``weights`` (a checkpoint file or folder;
    None: ``$MONA_VO_WEIGHTS``). A missing checkpoint raises the back end's BackendError."""
    from mona_vo.flow import FLOWS
    from mona_vo.masks import MaskConfig

    cls = FLOWS.get(name)
    if name == "dis":
        return cls(config=MaskConfig().dis)
    return cls(device=device, checkpoint=weights or None)


def evaluate_flow(image0: str | Path, image1: str | Path, gt: str | Path, *,
                  occlusions: str | Path | None = None, invalid: str | Path | None = None,
                  flow: str = "dis", weights: str | None = None, device: str = "cpu",
                  repeats: int = 5) -> FlowEvalResult:
    """End-point errors and speed of the flow back end ``flow`` from ``image0`` to ``image1``
    against the ``.flo`` file ``gt`` (optional Sintel occlusion and invalid PNGs)."""
    from data_tools.frames import decode_image
    from data_tools.masks_io import read_mask_png
    from data_tools.sintel_formats import read_flo

    if repeats < 1:
        raise EvalError("repeats must be at least 1")
    backend = build_flow(flow, weights=weights, device=device)   # fails first when unavailable
    im0, im1 = decode_image(Path(image0)), decode_image(Path(image1))
    gt_flow = read_flo(gt)
    h, w = gt_flow.shape[:2]
    for path, im in ((image0, im0), (image1, im1)):
        if im.shape[:2] != (h, w):
            raise EvalError(f"{path}: image is {im.shape[1]} x {im.shape[0]}, the ground-truth "
                            f"flow {gt} is {w} x {h}")
    valid = np.ones((h, w), bool)
    noc = np.ones((h, w), bool)
    for path, target in ((invalid, valid), (occlusions, noc)):
        if path is None:
            continue
        m = read_mask_png(path)
        if m.shape != (h, w):
            raise EvalError(f"{path}: mask is {m.shape[1]} x {m.shape[0]}, the flow is {w} x {h}")
        target &= ~m
    noc &= valid

    est = backend.compute(im0, im1)                     # warm-up (lazy allocations)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        est = backend.compute(im0, im1)
        times.append(time.perf_counter() - t0)
    use = valid & np.isfinite(gt_flow).all(axis=2)
    return FlowEvalResult(
        flow=flow,
        epe_noc=end_point_error(est, gt_flow, noc),
        epe_all=end_point_error(est, gt_flow, valid),
        ms_per_pair=1000.0 * float(np.median(times)),
        n_noc=int((noc & use).sum()),
        n_all=int(use.sum()),
        width=w, height=h,
        gt_mean_magnitude=float(np.linalg.norm(gt_flow[use], axis=1).mean()),
        repeats=repeats)
