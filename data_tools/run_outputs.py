"""Writing a run's results so that finished work is never lost and nothing is half-written.

Masks are written as frames finish, into a hidden temporary folder beside the output; the
trajectory, plots and report are written to temporary names. Only when the whole run succeeded
are they renamed into place, the report last (its presence means the run is complete). An error
or Ctrl-C removes the temporaries and leaves any earlier results in ``out_dir`` untouched.
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from data_tools.atomic import atomic_dir, write_text_atomic
from data_tools.masks_io import write_mask_png
from data_tools.tum import write_tum_trajectory


class RunOutputs:
    """Context manager collecting one run's outputs in ``out_dir``."""

    def __init__(self, out_dir: str | Path, *, write_masks: bool = True):
        self.out_dir = Path(out_dir)
        self.write_masks = write_masks
        self._tmp: Path | None = None

    def __enter__(self):
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self._tmp = Path(tempfile.mkdtemp(prefix=".partial-", dir=self.out_dir))
        os.chmod(self._tmp, 0o755)
        if self.write_masks:
            (self._tmp / "masks").mkdir()
        return self

    def __exit__(self, exc_type, exc, tb):
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
        return False

    @property
    def staging(self) -> Path:
        """Temporary folder for outputs that are moved into place by :meth:`commit`."""
        return self._tmp

    def add_mask(self, name: str, mask: np.ndarray | None) -> None:
        if self.write_masks and mask is not None:
            write_mask_png(self._tmp / "masks" / f"{name}.png", mask)

    def commit(self, *, timestamps, poses, report: dict, extra_files: dict[str, Path] = ()) -> None:
        """Move everything into ``out_dir``: masks folder, trajectory.txt, extra files (e.g.
        plots staged in :attr:`staging`), report.json last."""
        if self.write_masks:
            with atomic_dir(self.out_dir / "masks") as tmp_masks:
                tmp_masks.rmdir()
                (self._tmp / "masks").rename(tmp_masks)
        write_tum_trajectory(self.out_dir / "trajectory.txt", timestamps, poses)
        for name, src in dict(extra_files).items():
            Path(src).replace(self.out_dir / name)
        write_text_atomic(self.out_dir / "report.json", json.dumps(report, indent=2, default=_json_default) + "\n")


def _json_default(obj):
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
