"""CoTracker point tracker (Karaev et al.; CoTracker3, 2024), the MONA paper's tracking-any-point
network, behind the incremental :class:`mona_vo.tracking.Tracker` interface.

CoTracker tracks a set of query points through a clip. Fed one frame at a time, this back end
keeps the last ``window`` frames and, at every ``step``, re-runs the network over them (LEAP-VO's
sliding window, 8 frames there):

* a track whose start frame is still inside the window is queried there, at the pixel where it
  was added (``add_points``);
* an older track is re-queried at the window's first frame, at its last estimate there (the
  newest run's, which saw the most context).

The track's position at the new frame is the network's estimate there; its visibility is the
network's visibility output at the new frame (CoTrackerPredictor thresholds it at 0.9). A track
that is not visible, or has left the image, is reported once with ``visible=False`` and dropped,
as the interface asks. ``error`` (pixels) is how far the new run moved the track's estimate at the
previous frame from the one reported then: the disagreement between two overlapping windows,
CoTracker's counterpart of LK's forward-backward distance (0 for a track started at the previous
frame, whose position there is its query).

Pixels: CoTracker scales queries and tracks by ``(W' - 1) / (W - 1)`` between the input and its
internal resolution, i.e. pixel centres at integers, the convention of :mod:`mona_vo.conventions`;
no shift is applied.

The network: ``cotracker.predictor.CoTrackerPredictor(checkpoint=...)`` (CoTracker3 offline,
``scaled_offline.pth`` in ``$MONA_VO_WEIGHTS`` by default). The ``cotracker`` package is not on
PyPI: install it from facebookresearch/co-tracker. Grey frames (the VO passes grey images) are
repeated to three channels.
"""
from __future__ import annotations

import numpy as np

from mona_vo.errors import BackendError
from mona_vo.neural import require, torch_device
from mona_vo.neural.weights import resolve_checkpoint
from mona_vo.tracking import Tracker, TrackUpdate


def _rgb(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"cotracker needs (H, W, 3) uint8 RGB or (H, W) uint8 grey images, got "
                         f"{image.shape} {image.dtype}")
    return image


class CoTrackerTracker(Tracker):
    """Sliding-window CoTracker (module docstring).

    checkpoint:  the CoTracker3 checkpoint (file, or folder holding ``scaled_offline.pth``;
                 default ``$MONA_VO_WEIGHTS``). Ignored when ``predictor`` is given.
    device:      'cpu' (default) or 'cuda' / 'cuda:N'.
    window:      frames the network sees per step (the new frame and the ones before), >= 2.
    border_px:   tracks closer than this to the image border are lost, pixels.
    predictor:   instead of loading CoTracker, any callable with CoTrackerPredictor's contract:
                 ``predictor(video, queries=queries)`` with video (1, T, 3, H, W) float32 RGB in
                 [0, 255] and queries (1, N, 3) float32 ``t, x, y`` (frame in the clip, pixels)
                 returning tracks (1, T, N, 2) float32 pixels x, y and visibility (1, T, N) bool
                 (tests, or a caller sharing one network).
    """

    def __init__(self, checkpoint=None, device: str = "cpu", window: int = 8,
                 border_px: float = 0.0, predictor=None):
        if int(window) < 2:
            raise BackendError("cotracker: window must be at least 2 frames")
        what = "CoTracker tracker"
        self.window = int(window)
        self.border_px = float(border_px)
        self.checkpoint = None
        if predictor is None:
            self.checkpoint = resolve_checkpoint("cotracker", checkpoint)
        self._torch = require("torch", what)
        self.device = torch_device(device, what)
        if predictor is None:
            module = require("cotracker.predictor", what)
            try:
                predictor = module.CoTrackerPredictor(checkpoint=str(self.checkpoint))
            except Exception as exc:  # noqa: BLE001 - a wrong file fails in many ways
                raise BackendError(f"{what}: cannot load checkpoint {self.checkpoint} "
                                   f"({type(exc).__name__}: {str(exc).splitlines()[0]}); is it "
                                   f"the CoTracker3 offline model (scaled_offline.pth)?") from None
            predictor = predictor.to(self.device).eval()
        self._predictor = predictor
        self._frames: list[np.ndarray] = []            # the last `window` frames, newest last
        self._t = -1                                    # index of the current (newest) frame
        self._next_id = 0
        self._ids = np.zeros(0, np.int64)               # (N,) live track ids
        self._start = np.zeros(0, np.int64)             # (N,) frame index each track was added
        self._query = np.zeros((0, 2), np.float32)      # (N, 2) pixels where it was added
        self._hist = np.zeros((0, 0, 2), np.float32)    # (N, len(frames), 2) estimates, NaN unknown
        self._err = np.zeros(0, np.float32)             # (N,) last reported error, pixels

    # ------------------------------------------------------------------ interface
    def live(self) -> TrackUpdate:
        pts = self._hist[:, -1] if self._hist.shape[1] else self._query
        return TrackUpdate(self._ids.copy(), pts.astype(np.float32), np.ones(len(self._ids), bool),
                           self._err.copy())

    def add_points(self, points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, np.float32).reshape(-1, 2)
        n = len(points)
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        hist = np.full((n, self._hist.shape[1], 2), np.nan, np.float32)
        if hist.shape[1]:
            hist[:, -1] = points
        self._ids = np.concatenate([self._ids, ids])
        self._start = np.concatenate([self._start, np.full(n, max(self._t, 0), np.int64)])
        self._query = np.concatenate([self._query, points])
        self._hist = np.concatenate([self._hist, hist])
        self._err = np.concatenate([self._err, np.zeros(n, np.float32)])
        return ids

    def remove(self, ids: np.ndarray) -> None:
        self._keep(~np.isin(self._ids, np.asarray(ids, np.int64)))

    def step(self, image: np.ndarray) -> TrackUpdate:
        image = _rgb(image)
        if self._frames and self._frames[-1].shape != image.shape:
            # A new image size: nothing carries over.
            self._keep(np.zeros(len(self._ids), bool))
            self._frames = []
        self._frames.append(image)
        self._t += 1
        column = np.full((len(self._ids), 1, 2), np.nan, np.float32)
        self._hist = np.concatenate([self._hist, column], axis=1)
        if len(self._frames) > self.window:
            self._frames.pop(0)
            self._hist = self._hist[:, 1:]
        # Tracks added before the first frame start on it.
        fresh = np.isnan(self._hist[:, -1, 0]) & (self._start == self._t)
        self._hist[fresh, -1] = self._query[fresh]
        if len(self._frames) < 2 or len(self._ids) == 0:
            return self.live()
        return self._run()

    # ------------------------------------------------------------------ internals
    def _keep(self, keep: np.ndarray) -> None:
        self._ids, self._start = self._ids[keep], self._start[keep]
        self._query, self._hist, self._err = self._query[keep], self._hist[keep], self._err[keep]

    def _queries(self) -> np.ndarray:
        """(N, 3) float32 ``t, x, y`` in the clip of the buffered frames."""
        first = self._t - len(self._frames) + 1
        inside = self._start >= first
        q = np.empty((len(self._ids), 3), np.float32)
        q[:, 0] = np.where(inside, self._start - first, 0)
        q[:, 1:] = np.where(inside[:, None], self._query, self._hist[:, 0])
        # A re-queried track with no estimate at the window's first frame (cannot happen while
        # every step runs, kept for safety): its newest known position.
        bad = ~np.isfinite(q[:, 1:]).all(axis=1)
        for k in np.nonzero(bad)[0]:
            known = np.nonzero(np.isfinite(self._hist[k, :, 0]))[0]
            q[k, 0] = known[0] if len(known) else 0
            q[k, 1:] = self._hist[k, known[0]] if len(known) else self._query[k]
        return q

    def _run(self) -> TrackUpdate:
        torch = self._torch
        queries = self._queries()
        video = np.stack(self._frames)                                  # (T, H, W, 3) uint8
        with torch.inference_mode():
            v = torch.from_numpy(video).to(self.device).permute(0, 3, 1, 2)[None].float()
            q = torch.from_numpy(queries).to(self.device)[None]
            tracks, vis = self._predictor(v, queries=q)
            tracks = tracks[0].float().cpu().numpy()                    # (T, N, 2)
            vis = vis[0].cpu().numpy().astype(bool)                     # (T, N)
        T = len(self._frames)
        if tracks.shape != (T, len(self._ids), 2) or vis.shape != (T, len(self._ids)):
            raise BackendError(f"cotracker returned tracks {tracks.shape} and visibility "
                               f"{vis.shape} for {T} frames and {len(self._ids)} queries")
        new = tracks[-1].astype(np.float32)
        prev = self._hist[:, -2]
        err = np.linalg.norm(tracks[-2] - prev, axis=1)
        err = np.where(np.isfinite(err), err, 0.0).astype(np.float32)
        h, w = self._frames[-1].shape[:2]
        b = self.border_px
        inside = (new[:, 0] >= -0.5 + b) & (new[:, 0] <= w - 0.5 - b) & \
                 (new[:, 1] >= -0.5 + b) & (new[:, 1] <= h - 0.5 - b)
        ok = vis[-1] & inside & np.isfinite(new).all(axis=1)
        update = TrackUpdate(self._ids.copy(), new, ok, err)
        # The newest run's estimates replace the older ones from each track's query frame on.
        t0 = queries[:, 0].astype(int)
        later = np.arange(T)[None, :] >= t0[:, None]                    # (N, T)
        self._hist = np.where(later[..., None], tracks.transpose(1, 0, 2), self._hist)
        self._hist = self._hist.astype(np.float32)
        self._err = err
        self._keep(ok)
        return update
