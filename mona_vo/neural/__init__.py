"""Neural back ends, for users who have the checkpoints. Imported only when one is chosen.

* flow ``raft`` -> :class:`raft.RaftFlow`: torchvision (torch 2.14.1 + torchvision 0.29.1).
* detector ``yolo`` -> :class:`yolo.YoloDetector`: ultralytics (the ultralytics-opencv-headless
  build, which keeps opencv-python-headless).
* segmenter ``sam`` -> :class:`sam.SamSegmenter`: segment-anything.
* tracker :class:`cotracker.CoTrackerTracker`: cotracker (facebookresearch/co-tracker; not on
  PyPI).

Every back end takes ``checkpoint=`` (a local file; default: the documented file name in the
folder ``$MONA_VO_WEIGHTS``, see :mod:`mona_vo.neural.weights`) and ``device=`` (``'cpu'``, the
default, or ``'cuda'`` / ``'cuda:N'`` when torch sees a GPU). Nothing is downloaded at run time.

Importing this package (or any module in it) imports no torch and touches no GPU: each back end
imports its network package when it is built. A missing checkpoint is reported before that, so the
error is the same whether the package is installed or not. ``.ci/neural`` installs the tested set
of packages into ``.venv-neural`` and runs ``tests/test_neural.py`` with random weights.
"""
from __future__ import annotations

import importlib

from mona_vo.errors import BackendError

# What to install for each network package (the versions .ci/neural tests).
INSTALL_HINTS = {
    "torch": "pip install torch==2.14.1 torchvision==0.29.1",
    "torchvision": "pip install torch==2.14.1 torchvision==0.29.1",
    "ultralytics": "pip install ultralytics-opencv-headless==8.4.190 (keeps opencv-python-headless)",
    "segment_anything": "pip install segment-anything==1.0",
    "cotracker": "pip install git+https://github.com/facebookresearch/co-tracker (not on PyPI)",
}


def require(module: str, what: str):
    """Import ``module`` for the back end ``what``; a missing package is a :class:`BackendError`
    that says what to install."""
    top = module.split(".")[0]
    hint = INSTALL_HINTS.get(top, f"pip install {top}")
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        raise BackendError(f"{what} needs the package '{top}' ({exc}); install it: {hint}") from None
    except Exception as exc:  # noqa: BLE001 - e.g. torchvision built for another torch
        first = str(exc).splitlines()[0] if str(exc) else ""
        raise BackendError(f"{what}: '{module}' is installed but does not import "
                           f"({type(exc).__name__}: {first}); install the tested set: {hint}") from None


def torch_device(device: str, what: str):
    """``torch.device`` for ``'cpu'`` or ``'cuda'`` / ``'cuda:N'``; CUDA without a visible GPU, or
    any other name, is a :class:`BackendError`."""
    torch = require("torch", what)
    name = str(device).strip().lower()
    if name == "cpu":
        return torch.device("cpu")
    if name == "cuda" or name.startswith("cuda:"):
        if not torch.cuda.is_available():
            raise BackendError(f"{what}: device '{device}' asked for, but torch sees no CUDA GPU; "
                               f"use device=cpu")
        try:
            dev = torch.device(name)
        except RuntimeError:
            raise BackendError(f"{what}: device '{device}' is not a valid CUDA device") from None
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise BackendError(f"{what}: device '{device}' does not exist "
                               f"({torch.cuda.device_count()} CUDA GPU(s) visible)")
        return dev
    raise BackendError(f"{what}: unknown device '{device}'; use cpu or cuda[:N]")


def load_state_dict(path, what: str) -> dict:
    """The tensors of a checkpoint file, on the CPU (``weights_only``: no code runs on load).
    A dict holding the state dict under 'model' or 'state_dict' is unwrapped."""
    torch = require("torch", what)
    try:
        state = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the user's to fix
        raise BackendError(f"{what}: cannot read checkpoint {path} ({type(exc).__name__}: "
                           f"{str(exc).splitlines()[0] if str(exc) else ''})") from None
    for key in ("model", "state_dict"):
        if isinstance(state, dict) and isinstance(state.get(key), dict):
            state = state[key]
    if not isinstance(state, dict):
        raise BackendError(f"{what}: checkpoint {path} holds no state dict "
                           f"(got {type(state).__name__})")
    return state


def load_into(model, state: dict, path, what: str, hint: str = "") -> None:
    """``model.load_state_dict(state)`` (strict); a mismatch is a :class:`BackendError` naming the
    file and the first differing keys."""
    suffix = f"; {hint}" if hint else ""
    try:
        result = model.load_state_dict(state, strict=False)
    except RuntimeError as exc:  # tensor shapes differ
        first = next((ln.strip() for ln in str(exc).splitlines()[1:] if ln.strip()), str(exc))
        raise BackendError(f"{what}: checkpoint {path} does not fit the model ({first})"
                           + suffix) from None
    missing, unexpected = list(result.missing_keys), list(result.unexpected_keys)
    if missing or unexpected:
        detail = []
        if missing:
            detail.append(f"{len(missing)} missing keys, e.g. {missing[0]}")
        if unexpected:
            detail.append(f"{len(unexpected)} unexpected keys, e.g. {unexpected[0]}")
        raise BackendError(f"{what}: checkpoint {path} does not fit the model ({'; '.join(detail)})"
                           + suffix)
