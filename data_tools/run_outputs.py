"""Writing a run's results so that finished work is never lost and nothing is half-written.

Masks are written as frames finish, into a hidden temporary folder beside the output; the
trajectory, plots and report are written to temporary names. Only when the whole run succeeded
are they renamed into place, the report last (its presence means the run is complete). An error
or Ctrl-C removes the temporaries and leaves any earlier results in ``out_dir`` untouched.
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import tempfile
import threading
from pathlib import Path

import numpy as np

from data_tools.atomic import atomic_dir, write_text_atomic
from data_tools.masks_io import write_mask_png
from data_tools.tum import write_tum_trajectory
from mona_vo.errors import MonaVoError

# Files a run may leave in out_dir besides masks/, trajectory.txt and report.json. When the folder
# holds an earlier run (its report.json), the ones this run does not write are removed at commit,
# so that the folder never mixes two runs; files of a folder without a report are never touched.
_OPTIONAL_FILES = ("trajectory.png", "overlay.mp4")


@contextlib.contextmanager
def sigint_deferred():
    """Hold Ctrl-C (SIGINT) back while the block runs, then deliver it. Used around the renames
    of a commit and the removal of temporaries, which are short and must not stop half-way."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    if signal.getsignal(signal.SIGINT) is None:  # a handler not set from Python: leave it be
        yield
        return
    caught = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if caught:
            signal.raise_signal(signal.SIGINT)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


class RunOutputs:
    """Context manager collecting one run's outputs in ``out_dir``."""

    def __init__(self, out_dir: str | Path, *, write_masks: bool = True):
        self.out_dir = Path(out_dir)
        self.write_masks = write_masks
        self._tmp: Path | None = None

    def __enter__(self):
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            self._tmp = Path(tempfile.mkdtemp(prefix=".partial-", dir=self.out_dir))
        except OSError as exc:  # a file of that name, no permission, read-only or full disk
            raise MonaVoError(f"{self.out_dir}: cannot write the output folder "
                              f"({exc.strerror or exc})") from None
        os.chmod(self._tmp, 0o755)
        if self.write_masks:
            (self._tmp / "masks").mkdir()
        return self

    def __exit__(self, exc_type, exc, tb):
        if self._tmp is not None:
            with sigint_deferred():
                shutil.rmtree(self._tmp, ignore_errors=True)
        return False

    @property
    def staging(self) -> Path:
        """Temporary folder for outputs that are moved into place by :meth:`commit`."""
        return self._tmp

    def add_mask(self, name: str, mask: np.ndarray | None) -> None:
        if self.write_masks and mask is not None:
            try:
                write_mask_png(self._tmp / "masks" / f"{name}.png", mask)
            except OSError as exc:  # e.g. a full disk: one line, and the run stops cleanly
                raise MonaVoError(f"{self.out_dir}: cannot write mask {name}.png "
                                  f"({exc.strerror or exc})") from None

    def commit(self, *, timestamps, poses, report: dict, extra_files: dict[str, Path] = ()) -> None:
        """Move everything into ``out_dir``: masks folder, trajectory.txt, extra files (e.g.
        plots staged in :attr:`staging`), report.json last.

        Ctrl-C is held back until the commit is done, and an earlier run's report.json is removed
        first, so that even a crash half-way never leaves a report beside another run's files.
        Outputs of that earlier run which this one does not write (masks/, overlay.mp4) go too.
        """
        extra_files = dict(extra_files)
        text = json.dumps(report, indent=2, default=_json_default) + "\n"
        try:
            with sigint_deferred():
                earlier = _earlier_report(self.out_dir / "report.json")
                _remove(self.out_dir / "report.json")
                self._move_masks(earlier)
                write_tum_trajectory(self.out_dir / "trajectory.txt", timestamps, poses)
                for name in _OPTIONAL_FILES:
                    if earlier is not None and name not in extra_files:
                        _remove(self.out_dir / name)
                for name, src in extra_files.items():
                    Path(src).replace(self.out_dir / name)
                write_text_atomic(self.out_dir / "report.json", text)
        except OSError as exc:
            raise MonaVoError(f"{self.out_dir}: cannot write the results "
                              f"({exc.strerror or exc}); the folder holds no complete run") from None

    def commit_masks(self, report_name: str, report: dict) -> None:
        """Move the masks folder into place and write ``report_name`` last (``mona-vo masks``),
        with the same guarantees as :meth:`commit`."""
        text = json.dumps(report, indent=2, default=_json_default) + "\n"
        try:
            with sigint_deferred():
                _remove(self.out_dir / report_name)
                self._move_masks(None)
                write_text_atomic(self.out_dir / report_name, text)
        except OSError as exc:
            raise MonaVoError(f"{self.out_dir}: cannot write the masks ({exc.strerror or exc})") from None

    def _move_masks(self, earlier: dict | None) -> None:
        if self.write_masks:
            with atomic_dir(self.out_dir / "masks") as tmp_masks:
                tmp_masks.rmdir()
                (self._tmp / "masks").rename(tmp_masks)
        elif earlier is not None and earlier.get("masks", "none") != "none":
            _remove(self.out_dir / "masks")  # the earlier run's, which this run's report would claim


def _earlier_report(path: Path) -> dict | None:
    """The report of the run whose results ``out_dir`` holds, or None (no report, or not ours)."""
    try:
        report = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return report if isinstance(report, dict) and "mona_vo_version" in report else None


def _json_default(obj):
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
