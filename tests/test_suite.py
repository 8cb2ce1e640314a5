"""How the suite itself runs (README: two pytest-xdist workers on two cores)."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest


@pytest.mark.skipif(not os.environ.get("PYTEST_XDIST_WORKER"), reason="runs alone, not under xdist")
def test_each_worker_and_the_commands_it_starts_run_opencv_on_one_thread():
    import cv2

    assert cv2.getNumThreads() == 1
    child = subprocess.run([sys.executable, "-c", "import cv2; print(cv2.getNumThreads())"],
                           capture_output=True, text=True, check=True)
    assert child.stdout.strip() == "1"
