"""Trajectory pictures: top view (x-z, the ground plane of a camera looking along z) and side view
(z against -y, up is up in OpenCV's y-down frame), estimate against GT after Sim(3) alignment when
GT is known. Matplotlib is imported here only, with the file-only Agg back end."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from data_tools.atomic import atomic_path
from mona_vo.geometry import align_similarity


def align_sim3(est_xyz: np.ndarray, gt_xyz: np.ndarray) -> np.ndarray:
    """Umeyama Sim(3) alignment of (N, 3) positions onto GT (for drawing; the metrics use evo)."""
    s, R, t = align_similarity(est_xyz, gt_xyz)
    return s * np.asarray(est_xyz, np.float64) @ R.T + t


def plot_trajectory(path: str | Path, est_xyz: np.ndarray, gt_xyz: np.ndarray | None = None, *,
                    title: str = "", low_confidence: np.ndarray | None = None,
                    labels: tuple[str, str] = ("estimate", "ground truth")) -> Path:
    """Write a PNG with top and side views. est_xyz / gt_xyz: (N, 3) camera centres (world)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    est = np.asarray(est_xyz, float)
    if gt_xyz is not None and len(gt_xyz) == len(est) and len(est) >= 3:
        est = align_sim3(est, np.asarray(gt_xyz, float))
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5))
    views = (("top view", 0, 2, "x", "z"), ("side view", 2, 1, "z", "up (-y)"))
    for ax, (name, i, j, xl, yl) in zip(axes, views):
        sign = -1.0 if j == 1 else 1.0
        if gt_xyz is not None:
            ax.plot(gt_xyz[:, i], sign * gt_xyz[:, j], "-", color="0.5", lw=2, label=labels[1])
        ax.plot(est[:, i], sign * est[:, j], "-", color="tab:blue", lw=1.2, label=labels[0])
        ax.plot(est[:1, i], sign * est[:1, j], "o", color="tab:green", ms=5, label="start")
        if low_confidence is not None and np.any(low_confidence):
            lc = np.asarray(low_confidence, bool)
            ax.plot(est[lc, i], sign * est[lc, j], "x", color="tab:red", ms=5, label="low confidence")
        ax.set_title(name)
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return path
